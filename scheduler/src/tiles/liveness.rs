//! Where time alone acts on workers and jobs: workers that fell silent are dropped,
//! leases run out, workers that hold tiles late without a result are marked
//! unresponsive, and jobs no connected worker may serve fail after the stall timeout.
//! These checks run at a `Timeout` (and go on at a `Continue` when a call's allowance
//! of checks ran out) and judge what the other events left behind, so they read apart
//! from the events themselves. What a worker's message leaves for them (its last-heard
//! time) is kept here too.

use std::collections::BTreeSet;

use protocol::{JobId, WorkerId};

use super::{name_list, Action, Machine, Scheduler};

impl Scheduler {
    /// The worker was heard from: its last-heard time moves to now.
    pub(super) fn seen(&mut self, worker: WorkerId) {
        if let Some(w) = self.workers.get_mut(&worker) {
            if w.last_seen != self.now {
                // Only this worker's own entry at the front goes stale here.
                let front = self.by_last_seen.front() == Some((w.last_seen, worker));
                w.last_seen = self.now;
                self.by_last_seen.push(self.now, worker);
                if front {
                    self.trim_seen();
                }
            }
        }
    }

    /// Drops the stale entries at the front of `Scheduler::by_last_seen`: those of
    /// workers gone or heard from since. One check each: a long run of them is
    /// dropped over several calls, the front stale meanwhile (the next deadline is
    /// then early, never late).
    pub(super) fn trim_seen(&mut self) {
        while let Some((seen, worker)) = self.by_last_seen.front() {
            if self
                .workers
                .get(&worker)
                .is_some_and(|w| w.last_seen == seen)
                || !self.take_check()
            {
                break;
            }
            self.by_last_seen.pop_front();
        }
    }

    /// Takes one check from the call's allowance ([`Policy::checks_per_call`](super::Policy::checks_per_call));
    /// `false` when none is left, and then the call asks to be continued.
    pub(super) fn take_check(&mut self) -> bool {
        self.take_checks(1)
    }

    /// Takes `n` checks at once, for a step that costs as much.
    pub(super) fn take_checks(&mut self, n: usize) -> bool {
        if self.checks_left < n {
            self.checks_more = true;
            return false;
        }
        self.checks_left -= n;
        true
    }

    /// Drops the workers silent for longer than the heartbeat timeout, in id order.
    pub(super) fn check_heartbeats(&mut self, actions: &mut Vec<Action>) {
        let timeout = self.policy.heartbeat_timeout;
        let mut silent: Vec<WorkerId> = Vec::new();
        while let Some((seen, id)) = self.by_last_seen.front() {
            let live = self.workers.get(&id).is_some_and(|w| w.last_seen == seen);
            if (live && self.now.saturating_sub(seen) <= timeout) || !self.take_check() {
                break;
            }
            if live {
                silent.push(id);
            }
            self.by_last_seen.pop_front();
        }
        silent.sort_unstable();
        silent.dedup();
        for worker in silent {
            self.counters.workers_dropped += 1;
            actions.push(Action::DropWorker { worker });
            self.remove_worker(worker, actions);
        }
    }

    /// Puts back every tile whose only live lease has run out.
    pub(super) fn check_leases(&mut self) {
        let now = self.now;
        for job in self.jobs.values_mut() {
            let cut = job.expire_leases(
                now,
                &mut self.checks_left,
                &mut self.counters,
                &mut self.overdue,
            );
            if cut {
                self.checks_more = true;
                return;
            }
        }
    }

    /// Marks unresponsive, in id order, the workers that hold a tile late (under a lease
    /// that ran out, or a copy of a tile accepted from another worker since) and have
    /// returned no result for longer than their allowance: the greater of
    /// [`Policy::progress_timeout`] and [`Policy::progress_factor`] times their pace,
    /// the slowest of their own results and of the measured tiles of the jobs they
    /// hold. A slow worker's pace is slow, so it is given the time its own results show
    /// it needs; a worker that never returned anything is judged by the jobs' tiles,
    /// sixteen times over.
    ///
    /// [`Policy::progress_timeout`]: super::Policy::progress_timeout
    /// [`Policy::progress_factor`]: super::Policy::progress_factor
    pub(super) fn check_progress(&mut self, actions: &mut Vec<Action>) {
        let now = self.now;
        let (due, cut) = self.overdue.due(now, self.checks_left);
        self.checks_left -= due.len();
        self.checks_more |= cut;
        for id in due {
            let Some(w) = self.workers.get(&id) else {
                self.overdue.remove(id);
                continue;
            };
            // Not silent for the least allowance yet: it cannot be marked now, whatever
            // it holds, so what it holds is looked at only once it may be (a lease
            // running out on thousands of busy workers at once costs a lookup each).
            let least = w
                .progress_since
                .saturating_add(self.policy.progress_timeout);
            if !w.unresponsive && now <= least {
                self.overdue.defer(id, least.saturating_add(1));
                continue;
            }
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
                self.overdue.remove(id);
                continue;
            }
            // Not found unresponsive before its last progress plus the least
            // allowance; a worker marked already stays filed, so that once a result
            // makes it responsive again, what it still holds late is watched again.
            // Never again at this time: a call that goes on where the last stopped
            // looks at the others.
            let next = w
                .progress_since
                .saturating_add(self.policy.progress_timeout)
                .saturating_add(1)
                .max(now + 1);
            if w.unresponsive {
                self.overdue.defer(id, next);
                continue;
            }
            let allowance = self
                .policy
                .progress_timeout
                .max(pace.saturating_mul(self.policy.progress_factor));
            let silent = now.saturating_sub(w.progress_since);
            self.overdue.defer(id, next);
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
    pub(super) fn progressed(
        &mut self,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        actions: &mut Vec<Action>,
    ) {
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
    pub(super) fn check_stalls(&mut self, actions: &mut Vec<Action>) {
        let now = self.now;
        let mut failed = Vec::new();
        // A job with requirements counts only the ready machines that meet them; with
        // none of them connected it waits, as any job does with no worker at all.
        let ready_by_job = self.ready_by_job();
        for (&id, job) in &mut self.jobs {
            if self.paused.contains(&id) {
                job.stalled_since = None;
                continue;
            }
            let ready = ready_by_job.get(&id).unwrap_or(&self.ready);
            match job.stalled_tile(ready, self.policy.max_attempts) {
                None => job.stalled_since = None,
                Some(tile) => {
                    let since = *job.stalled_since.get_or_insert(now);
                    if now - since >= self.policy.stall_timeout {
                        let mut message = job.stall_message(tile, ready, self.policy.block_after);
                        if let Some(require) = self.requirements.get(&id) {
                            let tags: Vec<&str> = require.iter().map(String::as_str).collect();
                            message.push_str(&format!(
                                " (counting only the machines with every tag the job \
                                 requires: {})",
                                tags.join(", ")
                            ));
                        }
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
}
