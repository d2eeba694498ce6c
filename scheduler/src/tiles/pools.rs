//! Pools: worker tags and the tags a job requires. A worker that lacks any tag a job
//! requires is not eligible for that job's tiles, confirmations included; among the
//! eligible workers every other rule (priority, fair share, age, blocks, stalls) holds
//! as it is.
//!
//! Both sets are kept by id beside the state they qualify, not inside it: a job's
//! requirements hold from before its submission (like a pause) and across the runs of
//! a job rendered in several (passes, a retry); a worker's tags from before it joins,
//! so that its first fill already knows them.

use std::collections::{BTreeMap, BTreeSet};

use protocol::{JobId, WorkerId};

use super::{Action, Machine, Scheduler};

/// Tags, sorted and each once.
pub(super) type Tags = BTreeSet<String>;

/// Whether `tags` has every tag of `require` (nothing required: any worker).
pub(super) fn meets(tags: Option<&Tags>, require: Option<&Tags>) -> bool {
    match require {
        None => true,
        // A worker never told any tags has none: it meets only an empty requirement.
        Some(require) => require.is_empty() || tags.is_some_and(|t| require.is_subset(t)),
    }
}

impl Scheduler {
    /// [`Event::RequireTags`](super::Event::RequireTags): the job's tiles go only to
    /// workers with every tag of `tags` (none: any worker). A job already active keeps
    /// the tiles it has out; the next ones go by the new requirements.
    pub(super) fn set_requirements(
        &mut self,
        job: JobId,
        tags: Vec<String>,
        actions: &mut Vec<Action>,
    ) {
        if tags.is_empty() {
            self.requirements.remove(&job);
        } else {
            self.requirements.insert(job, tags.into_iter().collect());
        }
        // A job not yet submitted has nothing to hand out, and other jobs' tiles are
        // not for this event to move.
        if self.jobs.contains_key(&job) {
            self.fill_all(actions);
        }
    }

    /// [`Event::WorkerTags`](super::Event::WorkerTags): the worker's tags. Told before
    /// it joins; told again while it is connected, the tiles it holds of jobs it no
    /// longer qualifies for have their leases end at once (they go back to the queue
    /// for qualifying workers; its result still counts if it comes first, as for any
    /// lease that ran out).
    pub(super) fn set_worker_tags(
        &mut self,
        worker: WorkerId,
        tags: Vec<String>,
        actions: &mut Vec<Action>,
    ) {
        self.worker_tags.insert(worker, tags.into_iter().collect());
        let Some(w) = self.workers.get(&worker) else {
            return;
        };
        let held: Vec<(JobId, u32)> = w.holding.iter().copied().collect();
        let tags = self.worker_tags.get(&worker);
        let unqualified: Vec<(JobId, u32)> = held
            .into_iter()
            .filter(|(job, _)| !meets(tags, self.requirements.get(job)))
            .collect();
        for (job, tile) in unqualified {
            if let Some(j) = self.jobs.get_mut(&job) {
                let before = j.rank(job);
                j.expire_lease_of(tile, worker, &mut self.counters);
                self.rerank(job, before);
            }
        }
        self.fill_all(actions);
    }

    /// The machines ready for work (a live worker that is not draining) that may take
    /// the tiles of a job requiring `require`, with their count of such workers: what
    /// the stall check and the confirmations given up count, instead of every ready
    /// machine. Walks the workers: called once per distinct set of requirements at a
    /// timeout, not per event.
    pub(super) fn ready_with(&self, require: &Tags) -> BTreeMap<Machine, u32> {
        let mut ready = BTreeMap::new();
        for (id, w) in self.workers.iter() {
            if w.takes_tiles() && meets(self.worker_tags.get(id), Some(require)) {
                *ready.entry(w.machine.clone()).or_default() += 1;
            }
        }
        ready
    }

    /// The ready machines each job with requirements may count, by job (jobs without
    /// any count [`Scheduler::ready`] as it is).
    pub(super) fn ready_by_job(&self) -> BTreeMap<JobId, BTreeMap<Machine, u32>> {
        let mut by_set: BTreeMap<&Tags, BTreeMap<Machine, u32>> = BTreeMap::new();
        let mut out = BTreeMap::new();
        for (&job, require) in &self.requirements {
            if !self.jobs.contains_key(&job) {
                continue;
            }
            let ready = by_set
                .entry(require)
                .or_insert_with(|| self.ready_with(require));
            out.insert(job, ready.clone());
        }
        out
    }

    /// The tags the job requires, sorted (empty: none).
    pub fn requirements(&self, job: JobId) -> Vec<String> {
        self.requirements
            .get(&job)
            .map_or_else(Vec::new, |r| r.iter().cloned().collect())
    }

    /// The names of the machines that are ready for work (a live worker that is not
    /// draining, disabled, quarantined nor unresponsive) and have every tag of
    /// `require`: what clients are warned with while none, or for a job in full
    /// verification only one, qualifies. Walks the workers: called for a status.
    pub fn qualifying_machines(&self, require: &[String]) -> Vec<String> {
        let require: Tags = require.iter().cloned().collect();
        self.ready_with(&require)
            .keys()
            .map(ToString::to_string)
            .collect()
    }
}

impl Scheduler {
    /// The work left in each active job that is not paused, as (job, tiles not yet
    /// done: waiting, out on workers or held for confirmation), in id order: what an
    /// autoscaler is told waits in each pool (the job's [`Scheduler::requirements`]).
    /// A paused job is left out: workers started for it would have nothing to do.
    pub fn work_left(&self) -> Vec<(JobId, u32)> {
        self.jobs
            .iter()
            .filter(|(id, _)| !self.paused.contains(id))
            .map(|(&id, job)| (id, job.remaining))
            .collect()
    }

    /// The connected workers ready for work (not draining, disabled, quarantined nor
    /// unresponsive) that have every tag of `require`.
    pub fn qualifying_workers(&self, require: &[String]) -> u32 {
        let require: Tags = require.iter().cloned().collect();
        self.ready_with(&require).values().sum()
    }
}
