//! An active job's tiles: their queue, their leases and where each stands, with the
//! indexes that keep every decision about one job from walking all of its tiles. A
//! [`Job`] answers for itself alone (which tile next, which leases ran out, whether
//! it is stalled); the scheduler weighs jobs and workers against each other.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, VecDeque};

use protocol::{JobId, SceneHash, WorkerId};

use super::{name_list, ByTile, Counters, Machine, Millis, Overdue, Policy};

/// One assignment of a tile to a worker.
#[derive(Clone, Copy, Debug)]
pub(super) struct Lease {
    pub(super) worker: WorkerId,
    pub(super) started: Millis,
    /// When it runs out, for a lease given once the job's tiles were measured; one
    /// given before runs out at its start plus the job's
    /// [`Job::unmeasured_length`] (see [`Job::unmeasured`]).
    pub(super) deadline: Millis,
    /// Given before the job's first tile was measured.
    pub(super) unmeasured: bool,
    /// Ran out: the tile was put back in the queue, but this holder may still deliver.
    pub(super) expired: bool,
}

/// Where a tile of an active job stands. One byte per tile: a job of a million tiles
/// is mostly tiles waiting, and they should cost little more than their place in the
/// queue.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum TileState {
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
pub(super) type JobRank = (Reverse<i32>, usize, JobId);

pub(super) struct Job {
    pub(super) priority: i32,
    /// Renders for an interactive view ([`Event::Interactive`]).
    ///
    /// [`Event::Interactive`]: super::Event::Interactive
    pub(super) interactive: bool,
    pub(super) scene: SceneHash,
    /// The tiles waiting, in the order they are handed out. Accepting a tile that is
    /// still queued (its lease ran out, then its holder delivered) leaves its entry
    /// here rather than searching the queue for it; entries of done tiles are skipped,
    /// and dropped when met. A done tile waits again only when it is revoked (a
    /// quarantine); it is then put at the head, before any stale entry of its own, so
    /// the first entry of each waiting tile is its place in the queue.
    pub(super) waiting: VecDeque<u32>,
    /// The tiles waiting: the entries of `waiting` that are not stale.
    pub(super) queued: u32,
    pub(super) state: Vec<TileState>,
    /// Looked up on every result, every assignment and every lease's end, so hashed;
    /// what walks it in an order that decides or shows anything sorts first.
    pub(super) in_flight: ByTile<Vec<Lease>>,
    /// The tiles of `in_flight` with exactly one live lease, by [`straggler_key`] then
    /// number: the candidates for a copy, the one out longest first. Kept so that a
    /// worker with free credit finds its straggler without walking every tile in
    /// flight.
    pub(super) stragglers: BTreeSet<(Millis, u32)>,
    /// The live leases given once the job's tiles were measured, by deadline, so that
    /// a timeout looks only at those that ran out.
    deadlines: BTreeSet<(Millis, u32, WorkerId)>,
    /// The live leases given before the first tile was measured, by start: they all
    /// have one length, [`Job::unmeasured_length`], so their order by start is their
    /// order by deadline, and bringing that length down when the first tile is
    /// measured moves none of them.
    unmeasured: BTreeSet<(Millis, u32, WorkerId)>,
    /// The length of every lease of [`Job::unmeasured`]: the initial lease, then
    /// (once the first tile is measured) no more than the measured lease.
    unmeasured_length: Millis,
    pub(super) remaining: u32,
    /// Failures reported per tile, and the machines each tile failed on.
    pub(super) failures: BTreeMap<u32, (u32, BTreeSet<Machine>)>,
    /// Times each tile was lost with its worker.
    pub(super) losses: BTreeMap<u32, u32>,
    /// Since when (on the scheduler's clock) no connected worker may take any waiting
    /// tile, as last seen at a timeout.
    pub(super) stalled_since: Option<Millis>,
    /// Failures per machine, and the machines blocked from this job.
    pub(super) worker_failures: BTreeMap<Machine, u32>,
    pub(super) blocked: BTreeSet<Machine>,
    /// Holders of tiles already accepted, whose copies are still to come.
    pub(super) late_copies: BTreeSet<(u32, WorkerId)>,
    /// Tiles whose result is held for confirmation: the machine that rendered it (it
    /// may not confirm itself) and whether the confirmation is required.
    pub(super) held: BTreeMap<u32, (Machine, bool)>,
    /// Measured tile times (assignment to result).
    pub(super) measured: u32,
    pub(super) total_time: Millis,
    pub(super) slowest: Millis,
}

impl Job {
    pub(super) fn new(priority: i32, scene: SceneHash, tiles: u32) -> Job {
        Job {
            priority,
            interactive: false,
            scene,
            waiting: (0..tiles).collect(),
            queued: tiles,
            state: vec![TileState::Waiting; tiles as usize],
            in_flight: ByTile::default(),
            stragglers: BTreeSet::new(),
            deadlines: BTreeSet::new(),
            unmeasured: BTreeSet::new(),
            unmeasured_length: Millis::MAX,
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

    pub(super) fn rank(&self, id: JobId) -> JobRank {
        (Reverse(self.priority), self.in_flight.len(), id)
    }

    fn is_waiting(&self, tile: u32) -> bool {
        self.state.get(tile as usize) == Some(&TileState::Waiting)
    }

    /// Whether the tile's result is held from this machine, which may then not render
    /// it again.
    pub(super) fn held_from(&self, tile: u32, machine: &Machine) -> bool {
        self.held.get(&tile).is_some_and(|(m, _)| m == machine)
    }

    /// Puts a tile that is not done back at the head of the queue, unless it waits
    /// already. Returns whether it was put back.
    pub(super) fn requeue(&mut self, tile: u32) -> bool {
        debug_assert_ne!(self.state[tile as usize], TileState::Done);
        if self.is_waiting(tile) {
            return false;
        }
        self.waiting.push_front(tile);
        self.state[tile as usize] = TileState::Waiting;
        self.queued += 1;
        true
    }

    /// The workers holding any of its tiles: under a lease (live or run out) or as a
    /// copy still to come, each once, in id order.
    pub(super) fn holders(&self) -> BTreeSet<WorkerId> {
        self.in_flight
            .values()
            .flatten()
            .map(|l| l.worker)
            .chain(self.late_copies.iter().map(|(_, w)| *w))
            .collect()
    }

    pub(super) fn live_leases(&self, tile: u32) -> usize {
        self.in_flight
            .get(&tile)
            .map_or(0, |ls| ls.iter().filter(|l| !l.expired).count())
    }

    pub(super) fn lease_length(&self, policy: &Policy) -> Millis {
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
    /// then found out as soon as one on a working machine is. Those are the leases of
    /// [`Job::unmeasured`]: one length changes, whatever the tiles in flight.
    pub(super) fn shorten_leases(&mut self, length: Millis) {
        self.unmeasured_length = self.unmeasured_length.min(length);
    }

    /// The earliest deadline of a live lease.
    pub(super) fn first_deadline(&self) -> Option<Millis> {
        self.first_due().map(|((deadline, _, _), _)| deadline)
    }

    /// The live lease that runs out first, as (deadline, tile, worker), and whether it
    /// is one of [`Job::unmeasured`].
    fn first_due(&self) -> Option<((Millis, u32, WorkerId), bool)> {
        let measured = self.deadlines.first().map(|&key| (key, false));
        let unmeasured = self.unmeasured.first().map(|&(started, tile, worker)| {
            let deadline = started.saturating_add(self.unmeasured_length);
            ((deadline, tile, worker), true)
        });
        match (measured, unmeasured) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Takes a live lease out of the deadline indexes.
    fn unindex(&mut self, tile: u32, lease: &Lease) {
        if lease.unmeasured {
            self.unmeasured.remove(&(lease.started, tile, lease.worker));
        } else {
            self.deadlines.remove(&(lease.deadline, tile, lease.worker));
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

    /// Gives the worker a lease on the tile (`unmeasured` is the job's to set).
    pub(super) fn add_lease(&mut self, tile: u32, mut lease: Lease) {
        lease.unmeasured = self.measured == 0;
        if lease.unmeasured {
            // The initial lease: the same for every lease before the first measure.
            let length = lease.deadline.saturating_sub(lease.started);
            self.unmeasured_length = self.unmeasured_length.min(length);
            self.unmeasured.insert((lease.started, tile, lease.worker));
        } else {
            self.deadlines.insert((lease.deadline, tile, lease.worker));
        }
        let leases = self.in_flight.entry(tile).or_default();
        let before = straggler_key(leases);
        leases.push(lease);
        let after = straggler_key(leases);
        self.restraggle(tile, before, after);
    }

    /// Ends the worker's lease on the tile, if it has one.
    pub(super) fn remove_lease(&mut self, tile: u32, worker: WorkerId) -> Option<Lease> {
        let leases = self.in_flight.get_mut(&tile)?;
        let pos = leases.iter().position(|l| l.worker == worker)?;
        let before = straggler_key(leases);
        let lease = leases.remove(pos);
        let after = straggler_key(leases);
        if leases.is_empty() {
            self.in_flight.remove(&tile);
        }
        if !lease.expired {
            self.unindex(tile, &lease);
        }
        self.restraggle(tile, before, after);
        Some(lease)
    }

    /// Ends every lease on the tile, returning them.
    pub(super) fn take_leases(&mut self, tile: u32) -> Option<Vec<Lease>> {
        let leases = self.in_flight.remove(&tile)?;
        for l in leases.iter().filter(|l| !l.expired) {
            self.unindex(tile, l);
        }
        self.restraggle(tile, straggler_key(&leases), None);
        Some(leases)
    }

    /// Marks the leases whose deadline has come as run out, and puts back in the queue
    /// (in increasing tile order, each at the head) the tiles left with no live lease.
    /// Marks the leases due by `now` expired and requeues the tiles all of whose leases
    /// ran out; counts both.
    /// The workers whose leases ran out join `overdue`. At most `checks` leases run
    /// out, each taking one; returns whether more were due (the earliest go first).
    pub(super) fn expire_leases(
        &mut self,
        now: Millis,
        checks: &mut usize,
        counters: &mut Counters,
        overdue: &mut Overdue,
    ) -> bool {
        let mut due = Vec::new();
        let mut cut = false;
        while let Some(((deadline, tile, worker), unmeasured)) = self.first_due() {
            if deadline > now {
                break;
            }
            if *checks == 0 {
                cut = true;
                break;
            }
            *checks -= 1;
            if unmeasured {
                self.unmeasured.pop_first();
            } else {
                self.deadlines.pop_first();
            }
            due.push((tile, worker));
        }
        // Tile by tile, in increasing order, each tile's due leases at once.
        due.sort_unstable();
        let mut due = due.as_slice();
        while let Some(&(tile, _)) = due.first() {
            let ends = due.iter().take_while(|(t, _)| *t == tile).count();
            let leases = self
                .in_flight
                .get_mut(&tile)
                .expect("a live lease is in flight");
            let before = straggler_key(leases);
            for &(_, worker) in &due[..ends] {
                if let Some(lease) = leases.iter_mut().find(|l| l.worker == worker && !l.expired) {
                    lease.expired = true;
                    counters.leases_expired += 1;
                    overdue.insert(worker);
                }
            }
            due = &due[ends..];
            let all_expired = leases.iter().all(|l| l.expired);
            let after = straggler_key(leases);
            self.restraggle(tile, before, after);
            if all_expired && self.requeue(tile) {
                counters.tiles_requeued += 1;
            }
        }
        cut
    }

    /// Ends the worker's live lease on the tile now, if it has one, and puts the tile
    /// back in the queue if no live lease is left; counts both.
    pub(super) fn expire_lease_of(&mut self, tile: u32, worker: WorkerId, counters: &mut Counters) {
        let Some(leases) = self.in_flight.get_mut(&tile) else {
            return;
        };
        let before = straggler_key(leases);
        let Some(lease) = leases.iter_mut().find(|l| l.worker == worker && !l.expired) else {
            return;
        };
        lease.expired = true;
        let ended = *lease;
        counters.leases_expired += 1;
        let all_expired = leases.iter().all(|l| l.expired);
        let after = straggler_key(leases);
        self.unindex(tile, &ended);
        self.restraggle(tile, before, after);
        if all_expired && self.state[tile as usize] != TileState::Done && self.requeue(tile) {
            counters.tiles_requeued += 1;
        }
    }

    /// The first waiting tile this worker may take: one that has not failed on it and
    /// that it does not still hold under an expired lease.
    pub(super) fn take_waiting_for(&mut self, worker: WorkerId, machine: &Machine) -> Option<u32> {
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
    pub(super) fn stalled_tile(
        &self,
        ready: &BTreeMap<Machine, u32>,
        max_attempts: u32,
    ) -> Option<u32> {
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
    pub(super) fn stall_message(
        &self,
        tile: u32,
        ready: &BTreeMap<Machine, u32>,
        block_after: u32,
    ) -> String {
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
    pub(super) fn straggler_for(&self, worker: WorkerId, machine: &Machine) -> Option<u32> {
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
