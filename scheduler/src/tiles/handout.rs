//! Which tile goes to which worker: free credit filled by priority, fair share and
//! age, interactive jobs ahead of batch ones, stragglers copied, and each scene sent
//! before a worker's first tile of it and forgotten when no job uses it. The one
//! place tiles go out, kept apart from how they come back.

use std::collections::BTreeSet;
use std::ops::Bound::{Excluded, Unbounded};

use protocol::{JobId, SceneHash, WorkerId};

use super::pools::meets;
use super::{Action, Lease, Scheduler};

/// At most this many tiles in a row go to interactive jobs while batch tiles wait.
pub const INTERACTIVE_RUN: u32 = 4;

/// Checks a scene forgotten by one worker counts for: it touches that worker's own
/// state, spread over the farm's memory, where a lease running out touches its job's.
const FORGET_COST: usize = 4;

impl Scheduler {
    /// After a job ended: the workers that have a scene no active job uses are to be
    /// told to forget it ([`Scheduler::forget_pending`]).
    pub(super) fn forget_unused_scenes(&mut self, actions: &mut Vec<Action>) {
        let in_use: BTreeSet<SceneHash> = self.jobs.values().map(|j| j.scene).collect();
        for scene in self.scene_holders.keys() {
            if !in_use.contains(scene) && !self.forgetting.contains(scene) {
                self.forgetting.push_back(*scene);
            }
        }
        self.forget_pending(actions);
    }

    /// Tells the holders of scenes no active job uses to forget them, [`FORGET_COST`]
    /// checks each ([`Policy::checks_per_call`](super::Policy::checks_per_call)).
    /// Within the
    /// call's checks: in worker id order, each worker's scenes in order. Beyond them
    /// (a scene thousands of workers have): scene after scene, each in worker order,
    /// as many as the call allows, and the rest in the calls that follow. A scene in
    /// use again meanwhile stays with the workers not yet told. Only the workers that
    /// have such a scene are visited ([`Scheduler::scene_holders`]).
    pub(super) fn forget_pending(&mut self, actions: &mut Vec<Action>) {
        if self.forgetting.is_empty() {
            return;
        }
        let in_use: BTreeSet<SceneHash> = self.jobs.values().map(|j| j.scene).collect();
        let holders = &self.scene_holders;
        self.forgetting
            .retain(|s| !in_use.contains(s) && holders.contains_key(s));
        let pending: usize = self.forgetting.iter().map(|s| holders[s].len()).sum();
        if pending.saturating_mul(FORGET_COST) <= self.checks_left {
            self.checks_left -= pending * FORGET_COST;
            let mut forget: Vec<(WorkerId, SceneHash)> = Vec::with_capacity(pending);
            for scene in std::mem::take(&mut self.forgetting) {
                let holders = self.scene_holders.remove(&scene).unwrap_or_default();
                forget.extend(holders.into_iter().map(|worker| (worker, scene)));
            }
            forget.sort_unstable();
            for (worker, scene) in forget {
                self.forget_scene(worker, scene, actions);
            }
            return;
        }
        while let Some(&scene) = self.forgetting.front() {
            if !self.take_checks(FORGET_COST) {
                return;
            }
            let holders = self
                .scene_holders
                .get_mut(&scene)
                .expect("a scene being forgotten has holders");
            let worker = holders.pop_first().expect("holders are never empty");
            if holders.is_empty() {
                self.scene_holders.remove(&scene);
                self.forgetting.pop_front();
            }
            self.forget_scene(worker, scene, actions);
        }
    }

    /// The worker forgets the scene (it is out of the index already).
    fn forget_scene(&mut self, worker: WorkerId, scene: SceneHash, actions: &mut Vec<Action>) {
        let w = self
            .workers
            .get_mut(&worker)
            .expect("scene holders are live");
        w.scenes.remove(&scene);
        actions.push(Action::ForgetScene { worker, scene });
    }

    /// Takes the worker out of the index of the scenes it had.
    pub(super) fn unlist_scenes(&mut self, worker: WorkerId, scenes: &BTreeSet<SceneHash>) {
        for scene in scenes {
            if let Some(holders) = self.scene_holders.get_mut(scene) {
                holders.remove(&worker);
                if holders.is_empty() {
                    self.scene_holders.remove(scene);
                }
            }
        }
    }

    /// Fills every worker with free credit, in id order. Filling one worker changes
    /// no other worker's credit, so those full at the start are skipped, as filling
    /// them would give them nothing; and once no tile may go to anyone, the rest are
    /// not visited (they stay listed as hungry), so that a farm of many idle workers
    /// costs each event the number of jobs, not of workers.
    pub(super) fn fill_all(&mut self, actions: &mut Vec<Action>) {
        self.more = false;
        if self.storage_down || !self.anything_to_hand_out() {
            return;
        }
        // Walked in place, not copied: a call that stops at its bound must not pay for
        // every hungry worker of a large farm.
        let mut after = None;
        loop {
            let next = match after {
                None => self.hungry.first(),
                Some(last) => self.hungry.range((Excluded(last), Unbounded)).next(),
            };
            let Some(&worker) = next else {
                return;
            };
            after = Some(worker);
            let before = actions.len();
            self.fill(worker, actions);
            // Only a tile handed out can close the last one open.
            if actions.len() != before && !self.anything_to_hand_out() {
                self.more = false;
                return;
            }
            if self.more {
                // This call's share is out; the next call goes on from here.
                return;
            }
        }
    }

    /// Whether [`Scheduler::next_tile`] may find a tile for some worker: an active job
    /// that is not paused has a tile waiting, or (with speculation) none waiting and a
    /// straggler to copy. When not, it finds none for anyone.
    fn anything_to_hand_out(&self) -> bool {
        self.order.iter().any(|&(_, _, id)| {
            let job = &self.jobs[&id];
            !self.paused.contains(&id)
                && (job.queued > 0 || (self.policy.speculate && !job.stragglers.is_empty()))
        })
    }

    /// Gives the worker tiles until its credit is used or nothing is left for it.
    pub(super) fn fill(&mut self, worker_id: WorkerId, actions: &mut Vec<Action>) {
        if self.storage_down {
            // The worker stays hungry: `StorageAvailable` fills it.
            return;
        }
        loop {
            let Some(worker) = self.workers.get(&worker_id) else {
                self.hungry.remove(&worker_id);
                return;
            };
            if !worker.takes_tiles() || worker.holding.len() >= worker.credit {
                self.hungry.remove(&worker_id);
                return;
            }
            if self.handout_left == 0 {
                // The worker stays hungry: the next call fills it.
                self.more = true;
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
            let before = job.rank(job_id);
            let deadline = now + job.lease_length(&policy);
            job.add_lease(
                tile,
                Lease {
                    worker: worker_id,
                    started: now,
                    deadline,
                    unmeasured: false,
                    expired: false,
                },
            );
            let scene = job.scene;
            self.rerank(job_id, before);
            let worker = self.workers.get_mut(&worker_id).expect("checked above");
            if worker.scenes.insert(scene) {
                self.scene_holders
                    .entry(scene)
                    .or_default()
                    .insert(worker_id);
                actions.push(Action::SendScene {
                    worker: worker_id,
                    job: job_id,
                });
            }
            if worker.holding.is_empty() {
                // Idle until now: a result is due from now on, not since its last one.
                worker.progress_since = now;
            }
            worker.holding.insert((job_id, tile));
            actions.push(Action::Assign {
                worker: worker_id,
                job: job_id,
                tile,
            });
            self.handout_left -= 1;
        }
    }

    /// The next tile for the worker: a waiting tile of the best job (highest priority,
    /// then fewest tiles in flight, then oldest) it is not blocked from; failing that,
    /// a straggler to duplicate.
    fn next_tile(&mut self, worker: WorkerId) -> Option<(JobId, u32)> {
        let machine = &self.workers.get(&worker)?.machine;
        let tags = self.worker_tags.get(&worker);
        let requirements = &self.requirements;
        // Interactive jobs first; after a run of them, batch jobs first for one tile.
        let first_interactive = self.interactive_run < INTERACTIVE_RUN;
        for first in [true, false] {
            for &(_, _, id) in &self.order {
                let job = self.jobs.get_mut(&id).expect("ordered jobs are active");
                if first && job.interactive != first_interactive {
                    continue;
                }
                if self.paused.contains(&id)
                    || job.blocked.contains(machine)
                    || !meets(tags, requirements.get(&id))
                {
                    continue;
                }
                if let Some(tile) = job.take_waiting_for(worker, machine) {
                    self.interactive_run = if job.interactive {
                        self.interactive_run.saturating_add(1)
                    } else {
                        0
                    };
                    return Some((id, tile));
                }
            }
        }
        if !self.policy.speculate {
            return None;
        }
        let holding = &self.workers.get(&worker)?.holding;
        self.order.iter().find_map(|&(_, _, id)| {
            let job = &self.jobs[&id];
            if self.paused.contains(&id)
                || job.blocked.contains(machine)
                || job.queued > 0
                || !meets(tags, requirements.get(&id))
            {
                return None;
            }
            job.straggler_for(worker, machine)
                .filter(|t| !holding.contains(&(id, *t)))
                .map(|t| (id, t))
        })
    }
}
