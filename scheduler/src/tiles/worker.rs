//! The workers as the scheduler knows them: a [`Worker`]'s credit, the tiles it holds
//! and whether it takes tiles, and the [`Machine`] its failures count against. What
//! the scheduler remembers of each connection, apart from the decisions made with it.

use std::collections::{BTreeSet, HashMap};
use std::fmt;
use std::hash::BuildHasherDefault;

use protocol::{JobId, SceneHash, WorkerId};

use super::blocks::Blocks;
use super::sharded::{IdHasher, Sharded};
use super::Millis;

/// Who failures are counted against: the name a worker gave, or its connection.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum Machine {
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
pub(super) fn name_list(machines: &[&Machine]) -> String {
    const SHOWN: usize = 8;
    let printable = |m: &&Machine| m.to_string().replace(char::is_control, "?");
    let mut list: Vec<String> = machines.iter().take(SHOWN).map(printable).collect();
    if machines.len() > SHOWN {
        list.push(format!("and {} more", machines.len() - SHOWN));
    }
    list.join(", ")
}

pub(super) struct Worker {
    pub(super) machine: Machine,
    pub(super) threads: u32,
    pub(super) credit: usize,
    pub(super) holding: BTreeSet<(JobId, u32)>,
    pub(super) scenes: BTreeSet<SceneHash>,
    pub(super) draining: bool,
    /// Its machine is disabled by an operator: like draining, but undone by an enable.
    pub(super) disabled: bool,
    pub(super) last_seen: Millis,
    /// It holds tiles whose leases ran out and returned nothing for longer than its
    /// progress allowance: its heartbeats prove a connection, not that it renders. It
    /// gets no tile and counts for no one (see the [module doc](super)) until a result
    /// comes.
    pub(super) unresponsive: bool,
    /// Since when a result is due from it: its last result, or when it was last given
    /// a tile while holding none.
    pub(super) progress_since: Millis,
    /// The longest it took to return a result once it was free to work on it (since
    /// the tile's lease began or its previous result, whichever is later): its pace.
    pub(super) slowest_result: Millis,
}

impl Worker {
    /// Whether it may be given new tiles.
    pub(super) fn takes_tiles(&self) -> bool {
        !self.draining && !self.disabled && !self.unresponsive
    }
}

/// The workers whose progress a timeout checks (`Scheduler::overdue`), each filed under
/// the earliest time it could be found unresponsive: its last progress plus
/// [`Policy::progress_timeout`](super::Policy::progress_timeout), the least allowance
/// any worker has. Its progress only moves later and its allowance is never less, so
/// a timeout before that time could only find it in time: only the workers due are
/// looked at, not every worker holding a tile late on a farm of thousands. (A worker's
/// allowance shrinks when a job whose tiles it holds ends, taking that job's pace with
/// it: its holders are then looked at again at once, [`Overdue::sooner`].)
#[derive(Default)]
pub(super) struct Overdue {
    by_time: BTreeSet<(Millis, WorkerId)>,
    at: ByWorker<Millis>,
}

impl Overdue {
    /// Files the worker for the next timeout, unless it is filed already: its time
    /// still holds.
    pub(super) fn insert(&mut self, worker: WorkerId) {
        if self.at.insert_new(worker, 0) {
            self.by_time.insert((0, worker));
        }
    }

    pub(super) fn remove(&mut self, worker: WorkerId) {
        if let Some(at) = self.at.remove(&worker) {
            self.by_time.remove(&(at, worker));
        }
    }

    /// Makes room for one entry per worker of a farm of `workers`, ahead of need:
    /// the table grows while workers join (when few are filed) rather than when a
    /// lease runs out on thousands of them at once.
    pub(super) fn reserve(&mut self, workers: usize) {
        self.at.reserve(workers.saturating_sub(self.at.len()));
    }

    /// Files the worker to be looked at again at `at`.
    pub(super) fn defer(&mut self, worker: WorkerId, at: Millis) {
        if let Some(filed) = self.at.insert(worker, at) {
            self.by_time.remove(&(filed, worker));
        }
        self.by_time.insert((at, worker));
    }

    /// Looks at a filed worker again by `at`, if it is filed for later; a worker not
    /// filed stays so (it holds nothing late).
    pub(super) fn sooner(&mut self, worker: WorkerId, at: Millis) {
        if self.at.get(&worker).is_some_and(|&filed| filed > at) {
            self.defer(worker, at);
        }
    }

    /// The workers due by `now`, the `most` filed earliest, in id order; and whether
    /// more are due.
    pub(super) fn due(&self, now: Millis, most: usize) -> (Vec<WorkerId>, bool) {
        let mut filed = self.by_time.iter().take_while(|(at, _)| *at <= now);
        let mut due: Vec<WorkerId> = filed
            .by_ref()
            .take(most)
            .map(|&(_, worker)| worker)
            .collect();
        let more = filed.next().is_some();
        due.sort_unstable();
        (due, more)
    }
}

/// A map keyed by worker id, hashed with [`IdHasher`], in shards: a join never moves
/// every worker's state at once.
pub(crate) type ByWorker<V> = Sharded<WorkerId, V>;

/// A map keyed by a job's tile number, hashed with [`IdHasher`]. One table, unlike
/// [`ByWorker`]: it holds no more than a job's tiles in flight, whose growth moves small
/// entries in tens of microseconds, and it is looked up on every result and assignment,
/// which shards made dearer (5 % of the core's time at 5,000 workers).
pub(super) type ByTile<V> = HashMap<u32, V, BuildHasherDefault<IdHasher>>;

/// When each worker was heard from, oldest first: every message appends the worker at
/// the time it came (the clock never goes back), so the queue stays in order. An entry
/// older than its worker's last one is stale, for the owner to drop when it reaches
/// the front. Of the entries of one millisecond, the last appended comes first. The
/// entries and the runs of each millisecond are kept in small reused [`Blocks`], so
/// the queue never grows by copying a whole farm's entries, nor frees a large buffer,
/// in one call.
#[derive(Default)]
pub(super) struct SeenQueue {
    /// Per millisecond, oldest first: the time, how many of its entries are left and
    /// how many it had. The oldest one's are the first of `workers`, those left first
    /// (the last appended is dropped first).
    runs: Blocks<(Millis, usize, usize)>,
    /// The workers, in the order appended.
    workers: Blocks<WorkerId>,
}

impl SeenQueue {
    /// The worker was heard from at `now`.
    pub(super) fn push(&mut self, now: Millis, worker: WorkerId) {
        match self.runs.back_mut() {
            Some((at, left, all)) if *at == now => {
                // The newest run's entries are the last ones: one dropped already (if
                // it is the oldest too) is overwritten.
                let index = self.workers.len() - *all + *left;
                *left += 1;
                match self.workers.get_mut(index) {
                    Some(slot) => *slot = worker,
                    None => {
                        self.workers.push_back(worker);
                        *all += 1;
                    }
                }
            }
            _ => {
                self.runs.push_back((now, 1, 1));
                self.workers.push_back(worker);
            }
        }
    }

    /// The front entry: of the oldest time, the last worker appended then.
    pub(super) fn front(&self) -> Option<(Millis, WorkerId)> {
        let &(at, left, _) = self.runs.front()?;
        self.workers.get(left - 1).map(|&worker| (at, worker))
    }

    /// Drops the front entry.
    pub(super) fn pop_front(&mut self) {
        if let Some((_, left, all)) = self.runs.front_mut() {
            *left -= 1;
            if *left == 0 {
                let all = *all;
                self.runs.pop_front();
                self.workers.advance(all);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::VecDeque;

    use super::*;

    /// The queue as one growing list per millisecond, as it was first kept.
    #[derive(Default)]
    struct Buckets(VecDeque<(Millis, Vec<WorkerId>)>);

    impl Buckets {
        fn push(&mut self, now: Millis, worker: WorkerId) {
            match self.0.back_mut() {
                Some((at, workers)) if *at == now => workers.push(worker),
                _ => self.0.push_back((now, vec![worker])),
            }
        }

        fn front(&self) -> Option<(Millis, WorkerId)> {
            let (at, workers) = self.0.front()?;
            workers.last().map(|&worker| (*at, worker))
        }

        fn pop_front(&mut self) {
            if let Some((_, workers)) = self.0.front_mut() {
                workers.pop();
                if workers.is_empty() {
                    self.0.pop_front();
                }
            }
        }
    }

    #[test]
    fn the_queue_gives_its_entries_in_the_order_of_one_list_per_millisecond() {
        let mut queue = SeenQueue::default();
        let mut model = Buckets::default();
        let mut now = 0;
        let mut state = 7u64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            state >> 33
        };
        for step in 0..20_000u64 {
            match next() % 10 {
                // Bursts in one millisecond, some after part of it was dropped.
                0..=4 => {
                    for _ in 0..next() % 300 {
                        let worker = next() % 5_000;
                        queue.push(now, worker);
                        model.push(now, worker);
                    }
                }
                5 | 6 => now += next() % 3,
                _ => {
                    for _ in 0..next() % 600 {
                        queue.pop_front();
                        model.pop_front();
                    }
                }
            }
            assert_eq!(queue.front(), model.front(), "step {step}");
        }
    }
}
