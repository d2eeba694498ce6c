//! How a tile's fate is taken in: a result accepted (and the job done with its last),
//! tiles an operator has rendered again, a failure counted against the tile and its
//! machine, a tile lost with its worker, and the end of a job. Everything that moves a
//! tile towards done or puts it back, once it is out.

use std::collections::BTreeSet;

use protocol::{JobId, WorkerId};

use super::{Action, Lease, Machine, Scheduler, TileState};

impl Scheduler {
    /// Ends the worker's lease on the tile if it holds one for an active job, and
    /// returns it. Anything else (a stray or late message) changes nothing.
    pub(super) fn release(&mut self, worker: WorkerId, job_id: JobId, tile: u32) -> Option<Lease> {
        let job = self.jobs.get_mut(&job_id)?;
        let before = job.rank(job_id);
        let lease = job.remove_lease(tile, worker)?;
        self.rerank(job_id, before);
        self.drop_holding(worker, job_id, tile);
        Some(lease)
    }

    pub(super) fn tile_done(
        &mut self,
        worker: WorkerId,
        job_id: JobId,
        tile: u32,
        actions: &mut Vec<Action>,
    ) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        if job.late_copies.remove(&(tile, worker)) {
            self.drop_holding(worker, job_id, tile);
            actions.push(Action::DuplicateResult { job: job_id, tile });
            return;
        }
        // Only a held tile asks whose result it is (the machine's name is not cloned
        // for every result).
        let held = !job.held.is_empty();
        let own = held && self.jobs[&job_id].held_from(tile, &self.machine_of(worker));
        if own {
            // A machine does not confirm its own result: this copy only frees its slot.
            self.release_unconfirming(worker, job_id, tile);
            return;
        }
        let Some(lease) = self.release(worker, job_id, tile) else {
            return;
        };
        let job = self.jobs.get_mut(&job_id).expect("release checked the job");
        job.held.remove(&tile);
        let took = self.now.saturating_sub(lease.started);
        job.measured += 1;
        job.total_time += took;
        job.slowest = job.slowest.max(took);
        if job.measured == 1 {
            let length = job.lease_length(&self.policy);
            job.shorten_leases(length);
        }
        // Still queued if its lease ran out: its entry there is now stale.
        if job.state[tile as usize] == TileState::Waiting {
            job.queued -= 1;
        }
        job.state[tile as usize] = TileState::Done;
        job.remaining -= 1;
        // Other holders' copies are still to come: they will be compared.
        let before = job.rank(job_id);
        if let Some(others) = job.take_leases(tile) {
            for other in others {
                job.late_copies.insert((tile, other.worker));
                self.overdue.insert(other.worker);
            }
        }
        let finished = job.remaining == 0;
        self.rerank(job_id, before);
        actions.push(Action::AcceptTile { job: job_id, tile });
        if finished {
            let job = self.remove_job(job_id).expect("checked above");
            let holders: BTreeSet<WorkerId> = job.late_copies.iter().map(|(_, w)| *w).collect();
            for holder in holders {
                if let Some(w) = self.workers.get_mut(&holder) {
                    w.holding.retain(|(j, _)| *j != job_id);
                    self.hungry.insert(holder);
                    actions.push(Action::CancelOnWorker {
                        worker: holder,
                        job: job_id,
                    });
                }
            }
            actions.push(Action::JobDone { job: job_id });
            self.forget_unused_scenes(actions);
        }
    }

    /// Takes the tiles back from wherever they are and puts them at the head of the
    /// queue (see [`Event::RequeueTiles`]).
    ///
    /// [`Event::RequeueTiles`]: super::Event::RequeueTiles
    pub(super) fn requeue_tiles(&mut self, job_id: JobId, tiles: &[u32]) {
        for &tile in tiles {
            let Some(job) = self.jobs.get_mut(&job_id) else {
                return;
            };
            if tile as usize >= job.state.len() {
                continue;
            }
            let before = job.rank(job_id);
            // Every holder lets go: a result it still sends is a stray, which counts for
            // nothing (as after a cancel).
            let leases = job.take_leases(tile).unwrap_or_default();
            let copies: Vec<WorkerId> = job
                .late_copies
                .range((tile, WorkerId::MIN)..=(tile, WorkerId::MAX))
                .map(|&(_, w)| w)
                .collect();
            for &worker in &copies {
                job.late_copies.remove(&(tile, worker));
            }
            job.held.remove(&tile);
            if job.state[tile as usize] == TileState::Done {
                job.state[tile as usize] = TileState::Out;
                job.remaining += 1;
            }
            if job.requeue(tile) {
                self.counters.tiles_requeued += 1;
            }
            self.rerank(job_id, before);
            for worker in leases.iter().map(|l| l.worker).chain(copies) {
                self.drop_holding(worker, job_id, tile);
            }
        }
    }

    /// Counts a failure a worker reported for a tile (already released): retry it
    /// elsewhere, block a machine that keeps failing, or fail the job.
    pub(super) fn failed_attempt(
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
        } else if job.live_leases(tile) == 0 && job.requeue(tile) {
            self.counters.tiles_requeued += 1;
        }
    }

    /// Counts a loss of a tile (already released) with its worker: retry it, or fail
    /// the job when the tile has been lost too often.
    pub(super) fn lost(&mut self, job_id: JobId, tile: u32, actions: &mut Vec<Action>) {
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
        } else if job.live_leases(tile) == 0 && job.requeue(tile) {
            self.counters.tiles_requeued += 1;
        }
    }

    /// Removes an active job, telling the workers that hold its tiles to drop them.
    pub(super) fn end_job(&mut self, job_id: JobId, actions: &mut Vec<Action>) {
        let Some(job) = self.remove_job(job_id) else {
            return;
        };
        for worker in job.holders() {
            if let Some(w) = self.workers.get_mut(&worker) {
                w.holding.retain(|(j, _)| *j != job_id);
                self.hungry.insert(worker);
                // Its pace may have been this job's: its allowance may be less now.
                self.overdue.sooner(worker, self.now);
                actions.push(Action::CancelOnWorker {
                    worker,
                    job: job_id,
                });
            }
        }
        self.forget_unused_scenes(actions);
    }
}
