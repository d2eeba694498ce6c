//! Jobs submitted after others (`tessera submit --after JOB`): which wait, for what.
//!
//! A job's dependencies are fixed when it is submitted, and each must be a job the
//! coordinator already has: a dependency is always an older job, so no cycle can form,
//! whatever is submitted, retried or restarted. The [`Farm`](super::Farm) decides with
//! this record:
//!
//! - a stored job whose dependencies are not all done **waits**: its tiles are not
//!   handed out;
//! - a dependency's end, once written, **releases** the jobs waiting only for it
//!   (done), or **fails** them with a message naming it (failed or cancelled): no job
//!   waits for a job that has ended, so none waits forever;
//! - a dependency may not be deleted while a job that depends on it is not done, so a
//!   job that may still need its dependencies (waiting, running, or failed and to be
//!   retried) always finds them;
//! - retrying a job that failed because of a dependency needs the dependency retried
//!   first: the job then waits for it again, and the chain goes on.
//!
//! Nothing here is stored on its own: the dependencies are stored with each job, and
//! the waiting sets follow from the jobs' states, so a restarted coordinator decides
//! again from what it restored and decides the same.

use std::collections::{BTreeMap, BTreeSet};

use protocol::JobId;

/// Every job's dependencies, and the jobs waiting.
#[derive(Clone, Debug, Default)]
pub struct Dependencies {
    /// Each job submitted after others, until it is deleted: its dependencies.
    after: BTreeMap<JobId, Vec<JobId>>,
    /// The reverse: each dependency, the jobs submitted after it.
    dependents: BTreeMap<JobId, BTreeSet<JobId>>,
    /// Jobs waiting, with the dependencies not yet done.
    waiting: BTreeMap<JobId, BTreeSet<JobId>>,
}

impl Dependencies {
    /// Records that `job` was submitted after `after` (none: nothing recorded).
    pub fn declare(&mut self, job: JobId, after: &[JobId]) {
        if after.is_empty() {
            return;
        }
        let mut unique: Vec<JobId> = after.to_vec();
        unique.sort_unstable();
        unique.dedup();
        for &dependency in &unique {
            self.dependents.entry(dependency).or_default().insert(job);
        }
        self.after.insert(job, unique);
    }

    /// The jobs `job` was submitted after, in increasing order.
    pub fn after(&self, job: JobId) -> &[JobId] {
        self.after.get(&job).map_or(&[], Vec::as_slice)
    }

    /// The jobs submitted after `dependency`.
    pub fn dependents(&self, dependency: JobId) -> impl Iterator<Item = JobId> + '_ {
        self.dependents
            .get(&dependency)
            .into_iter()
            .flat_map(|d| d.iter().copied())
    }

    /// The dependencies `job` still waits for, while it waits.
    pub fn waiting_for(&self, job: JobId) -> Option<&BTreeSet<JobId>> {
        self.waiting.get(&job)
    }

    /// The jobs waiting, with what each waits for.
    pub fn waiting(&self) -> impl Iterator<Item = (JobId, &BTreeSet<JobId>)> + '_ {
        self.waiting.iter().map(|(&job, on)| (job, on))
    }

    /// `job` waits for `on` (not empty).
    pub fn wait(&mut self, job: JobId, on: BTreeSet<JobId>) {
        debug_assert!(!on.is_empty());
        self.waiting.insert(job, on);
    }

    /// `job` waits no more (released, or ended).
    pub fn stop_waiting(&mut self, job: JobId) -> bool {
        self.waiting.remove(&job).is_some()
    }

    /// `dependency` is done: the jobs waiting for it wait for it no more; those left
    /// waiting for nothing are returned, in increasing order, no longer waiting.
    pub fn done(&mut self, dependency: JobId) -> Vec<JobId> {
        let mut released = Vec::new();
        for dependent in self.dependents(dependency).collect::<Vec<_>>() {
            if let Some(on) = self.waiting.get_mut(&dependent) {
                on.remove(&dependency);
                if on.is_empty() {
                    self.waiting.remove(&dependent);
                    released.push(dependent);
                }
            }
        }
        released
    }

    /// The waiting jobs that wait for `dependency`, in increasing order.
    pub fn waiting_on(&self, dependency: JobId) -> Vec<JobId> {
        self.dependents(dependency)
            .filter(|d| {
                self.waiting
                    .get(d)
                    .is_some_and(|on| on.contains(&dependency))
            })
            .collect()
    }

    /// `job` is deleted: it is forgotten as a dependent (its dependencies may go).
    /// As a dependency it is forgotten too: only a job whose dependents are all done
    /// or deleted may be deleted.
    pub fn forget(&mut self, job: JobId) {
        self.waiting.remove(&job);
        if let Some(after) = self.after.remove(&job) {
            for dependency in after {
                if let Some(d) = self.dependents.get_mut(&dependency) {
                    d.remove(&job);
                    if d.is_empty() {
                        self.dependents.remove(&dependency);
                    }
                }
            }
        }
        self.dependents.remove(&job);
    }
}
