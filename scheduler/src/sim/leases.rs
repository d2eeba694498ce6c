//! The leases, as the daemon could work them out from what it sent and received.
//!
//! The scheduler does not report a lease running out (the tile just goes back to the
//! queue), so the simulation keeps its own account with the scheduler's documented
//! rule, and checks it against every assignment and result: a tile given again while
//! held must be a straggler copy (one live holder) or a requeue (every lease ran out),
//! and a result is accepted exactly when its sender holds a lease. Any disagreement is
//! counted in `Outcome::model_mismatches`. The account is a second, independent
//! reading of the rule, so it is kept apart from everything it checks.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap};

use protocol::{JobId, WorkerId};

use crate::tiles::{Millis, Policy};

pub(super) struct ModelLease {
    worker: WorkerId,
    started: Millis,
    deadline: Millis,
    expired: bool,
}

pub(super) enum AssignKind {
    First,
    AfterLoss,
    AfterExpiry,
    Speculative,
    Unexplained,
}

#[derive(Default)]
pub(super) struct LeaseModel {
    pub(super) policy: Policy,
    pub(super) now: Millis,
    pub(super) leases: BTreeMap<(JobId, u32), Vec<ModelLease>>,
    pub(super) by_worker: BTreeMap<WorkerId, BTreeSet<(JobId, u32)>>,
    pub(super) deadlines: BinaryHeap<Reverse<(Millis, JobId, u32, WorkerId)>>,
    /// Per job: accepted results measured, their total time and the slowest.
    pub(super) measured: BTreeMap<JobId, (u32, Millis, Millis)>,
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
    pub(super) fn expire(&mut self, now: Millis) -> u64 {
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

    pub(super) fn assign(
        &mut self,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        before: bool,
    ) -> AssignKind {
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

    pub(super) fn holds(&self, worker: WorkerId, job: JobId, tile: u32) -> bool {
        self.leases
            .get(&(job, tile))
            .is_some_and(|ls| ls.iter().any(|l| l.worker == worker))
    }

    /// The first result: measured, and every lease on the tile ends (the other holders'
    /// copies are late copies now).
    pub(super) fn accepted(&mut self, worker: WorkerId, job: JobId, tile: u32) {
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
    pub(super) fn expire_worker(&mut self, worker: WorkerId) -> u64 {
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

    pub(super) fn remove_worker(&mut self, worker: WorkerId) {
        for key in self.by_worker.remove(&worker).unwrap_or_default() {
            if let Some(leases) = self.leases.get_mut(&key) {
                leases.retain(|l| l.worker != worker);
                if leases.is_empty() {
                    self.leases.remove(&key);
                }
            }
        }
    }

    pub(super) fn end_job(&mut self, job: JobId) {
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
