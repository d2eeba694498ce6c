//! Results confirmed by another machine, and machines caught lying: a result held
//! until another machine's equal one comes, held results given up when no machine may
//! confirm them, and the quarantine of a machine that returned wrong pixels. The
//! rules of trust between machines, apart from the plain acceptance of results.

use protocol::{JobId, WorkerId};

use super::{Action, Lease, Machine, Scheduler, TileState};

impl Scheduler {
    /// A result to be confirmed by another machine: held, and the tile goes back to the
    /// queue for the others unless another machine is rendering it already.
    pub(super) fn tile_to_confirm(
        &mut self,
        worker: WorkerId,
        job_id: JobId,
        tile: u32,
        required: bool,
        actions: &mut Vec<Action>,
    ) {
        let machine = self.machine_of(worker);
        match self.jobs.get(&job_id).and_then(|j| j.held.get(&tile)) {
            // Held from another machine: the daemon compares before it asks for a
            // confirmation, so this is one.
            Some((from, _)) if *from != machine => {
                return self.tile_done(worker, job_id, tile, actions);
            }
            Some(_) => return self.release_unconfirming(worker, job_id, tile),
            None => {}
        }
        if self
            .jobs
            .get(&job_id)
            .is_some_and(|j| j.late_copies.contains(&(tile, worker)))
        {
            // Already accepted: this is a straggler's copy, compared as such.
            return self.tile_done(worker, job_id, tile, actions);
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
        if job.live_leases(tile) == 0 && job.requeue(tile) {
            self.counters.tiles_requeued += 1;
        }
    }

    /// Frees the slot of a copy from the machine whose result is held (it cannot
    /// confirm itself); the tile goes back to the queue if no one else renders it.
    pub(super) fn release_unconfirming(&mut self, worker: WorkerId, job_id: JobId, tile: u32) {
        if self.release(worker, job_id, tile).is_some() {
            let job = self.jobs.get_mut(&job_id).expect("release checked the job");
            if job.live_leases(tile) == 0 && job.requeue(tile) {
                self.counters.tiles_requeued += 1;
            }
        }
    }

    /// Shuts the machine out: its workers get nothing more, their tiles and its held
    /// results go back to the queue, and so do the revoked done tiles.
    pub(super) fn quarantine(
        &mut self,
        machine: Machine,
        revoke: &[(JobId, u32)],
        actions: &mut Vec<Action>,
    ) {
        if !self.quarantined.insert(machine.clone()) {
            // Already shut out; revoked tiles still go back.
        }
        let mut workers: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| w.machine == machine)
            .map(|(&id, _)| id)
            .collect();
        workers.sort_unstable();
        for worker in workers {
            let w = self.workers.get_mut(&worker).expect("listed above");
            let was_ready = w.takes_tiles();
            w.draining = true;
            // It holds nothing afterwards, whatever its entries are about: a tile of an
            // active job, a late copy, or a stale entry no active job knows of (its
            // job's id was submitted again, and that job has ended since).
            let holding = std::mem::take(&mut w.holding);
            if was_ready {
                self.unready(&machine);
            }
            for (job, tile) in holding {
                if self.release(worker, job, tile).is_some() {
                    if let Some(j) = self.jobs.get_mut(&job) {
                        if j.live_leases(tile) == 0 && j.requeue(tile) {
                            self.counters.tiles_requeued += 1;
                        }
                    }
                } else if let Some(j) = self.jobs.get_mut(&job) {
                    j.late_copies.remove(&(tile, worker));
                }
            }
        }
        for job in self.jobs.values_mut() {
            let dropped: Vec<u32> = job
                .held
                .iter()
                .filter(|(_, (m, _))| *m == machine)
                .map(|(&t, _)| t)
                .collect();
            for tile in dropped {
                job.held.remove(&tile);
            }
        }
        for &(job_id, tile) in revoke {
            let Some(job) = self.jobs.get_mut(&job_id) else {
                continue;
            };
            if job.state.get(tile as usize) != Some(&TileState::Done) {
                continue;
            }
            let before = job.rank(job_id);
            job.state[tile as usize] = TileState::Out;
            job.remaining += 1;
            // Copies still to come are results again: their holders hold the tile
            // under leases that ran out (the first result wins, theirs included).
            let copies: Vec<WorkerId> = job
                .late_copies
                .range((tile, WorkerId::MIN)..=(tile, WorkerId::MAX))
                .map(|&(_, w)| w)
                .collect();
            for worker in copies {
                job.late_copies.remove(&(tile, worker));
                job.in_flight.entry(tile).or_default().push(Lease {
                    worker,
                    started: self.now,
                    deadline: self.now,
                    unmeasured: false,
                    expired: true,
                });
            }
            job.requeue(tile);
            self.counters.tiles_requeued += 1;
            self.rerank(job_id, before);
        }
        let _ = actions;
    }

    /// Accepts the held results of optional confirmations that no connected machine
    /// may give (every other machine is blocked from the job, failed the tile, or
    /// there is none), in job then tile order.
    pub(super) fn give_up_confirmations(&mut self, actions: &mut Vec<Action>) {
        let mut finished = Vec::new();
        let mut reranked = Vec::new();
        // Only machines that meet a job's requirements may confirm its tiles.
        let ready_by_job = self.ready_by_job();
        for (&id, job) in &mut self.jobs {
            if job.held.is_empty() {
                continue;
            }
            let ready = ready_by_job.get(&id).unwrap_or(&self.ready);
            let before = job.rank(id);
            let accepted: Vec<u32> = job
                .held
                .iter()
                .filter(|&(&t, (from, required))| {
                    !required
                        && job.live_leases(t) == 0
                        && !ready.keys().any(|m| {
                            m != from
                                && !job.blocked.contains(m)
                                && job.failures.get(&t).is_none_or(|(_, on)| !on.contains(m))
                        })
                })
                .map(|(&t, _)| t)
                .collect();
            for tile in accepted {
                job.held.remove(&tile);
                if job.state[tile as usize] == TileState::Waiting {
                    job.queued -= 1;
                }
                // Holders under leases that ran out: their copies are still to come.
                for other in job.take_leases(tile).into_iter().flatten() {
                    job.late_copies.insert((tile, other.worker));
                    self.overdue.insert(other.worker);
                }
                job.state[tile as usize] = TileState::Done;
                job.remaining -= 1;
                actions.push(Action::AcceptHeld { job: id, tile });
            }
            reranked.push((id, before));
            if job.remaining == 0 {
                finished.push(id);
            }
        }
        for (id, before) in reranked {
            self.rerank(id, before);
        }
        for id in finished {
            self.end_job(id, actions);
            actions.push(Action::JobDone { job: id });
        }
    }
}
