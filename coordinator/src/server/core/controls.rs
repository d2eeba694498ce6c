//! Operators' controls: a job paused, resumed, given a new priority or its tiles
//! requeued; a worker drained, a machine disabled or enabled; and a job's status as
//! clients see it.

use std::sync::Arc;

use protocol::{JobId, JobState, JobStatus, Refusal, ToWorker, WorkerId};
use scheduler::lifecycle::Phase;
use scheduler::Event;
use tracing::info;

use super::records::{rect_pixels, Controls};
use super::{unknown, Core, Shared, Write};

impl Core {
    /// An operator pauses (`true`) or resumes a job (or a sequence: its frames, see
    /// `set_sequence_paused`): its tiles stop going out at once
    /// (those out may finish), or go out again. Returns what to store before the
    /// change is acknowledged, or why the job cannot be paused or resumed. Pausing a
    /// paused job, or resuming one that is not, changes nothing and succeeds.
    pub fn set_paused(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        paused: bool,
    ) -> Result<Controls, Refusal> {
        if self.sequences.contains_key(&id) {
            return self.set_sequence_paused(sh, id, paused);
        }
        let verb = if paused { "paused" } else { "resumed" };
        self.check_controllable(id, verb)?;
        let record = self.jobs.get_mut(&id).ok_or_else(|| unknown(id))?;
        let changed = record.paused != paused;
        record.paused = paused;
        let controls = Controls {
            job: id,
            paused,
            priority: record.priority,
        };
        if changed {
            info!(job = id, "job {verb} by an operator");
            let event = if paused {
                Event::PauseJob { job: id }
            } else {
                Event::ResumeJob { job: id }
            };
            self.tiles_event(sh, event);
        }
        Ok(controls)
    }

    /// An operator gives a job a new priority: the next tiles handed out follow it.
    /// Returns what to store before the change is acknowledged, or why not.
    pub fn set_priority(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        priority: i32,
    ) -> Result<Controls, Refusal> {
        if self.sequences.contains_key(&id) {
            return self.set_sequence_priority(sh, id, priority);
        }
        self.check_controllable(id, "given a new priority")?;
        let record = self.jobs.get_mut(&id).ok_or_else(|| unknown(id))?;
        let changed = record.priority != priority;
        record.priority = priority;
        let controls = Controls {
            job: id,
            paused: record.paused,
            priority,
        };
        if changed {
            info!(
                job = id,
                priority, "job given a new priority by an operator"
            );
            self.tiles_event(sh, Event::SetPriority { job: id, priority });
        }
        Ok(controls)
    }

    /// Whether an operator may still change the job: it must be queued or running,
    /// with tiles still to hand out.
    fn check_controllable(&self, id: JobId, verb: &str) -> Result<(), Refusal> {
        let job = self.farm.lifecycle().job(id).ok_or_else(|| unknown(id))?;
        match &job.phase {
            Phase::Storing | Phase::Queued | Phase::Running => Ok(()),
            Phase::Finishing { .. } => Err(Refusal::state(format!(
                "job {id} cannot be {verb}: all its tiles are in and its image is being stored"
            ))),
            Phase::Ended { state, .. } => Err(ended_refusal(id, verb, *state)),
        }
    }

    /// An operator has tiles of a queued or running job rendered again, wherever they
    /// are (see [`Event::RequeueTiles`]): a done tile's result is dropped, from the
    /// frame's totals and from the disk. Returns what to store before the change is
    /// acknowledged (the stored tiles are forgotten before it, in the queue's order).
    pub fn requeue(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        tiles: &[u32],
        peer: std::net::IpAddr,
    ) -> Result<Controls, Refusal> {
        self.check_controllable(id, "requeued")?;
        let record = self.jobs.get_mut(&id).ok_or_else(|| unknown(id))?;
        if record.adaptive.is_some() {
            return Err(Refusal::invalid(format!(
                "job {id} cannot be requeued: an adaptive job renders in passes, whose \
                 tiles are not taken back one by one"
            )));
        }
        if tiles.is_empty() {
            return Err(Refusal::invalid(format!(
                "job {id}: name at least one tile to requeue"
            )));
        }
        let total = record.tiles_total;
        if let Some(bad) = tiles.iter().find(|&&t| t >= total) {
            return Err(Refusal::invalid(format!(
                "job {id} has tiles 0 to {}: there is no tile {bad}",
                total.saturating_sub(1)
            )));
        }
        let mut tiles = tiles.to_vec();
        tiles.sort_unstable();
        tiles.dedup();
        let mut forget = Vec::new();
        for &tile in &tiles {
            if let Some(a) = record.accepted.remove(&tile) {
                record.remove_cost(&a, rect_pixels(record.tiles[tile as usize]));
                record.tiles_recorded = record.tiles_recorded.saturating_sub(1);
                if let Some(count) = record.tiles_per_worker.get_mut(&*a.machine) {
                    *count = count.saturating_sub(1);
                }
                forget.push(tile);
            }
        }
        let controls = Controls {
            job: id,
            paused: record.paused,
            priority: record.priority,
        };
        self.held
            .retain(|&(j, t), _| j != id || tiles.binary_search(&t).is_err());
        for w in self.workers.values_mut() {
            w.assigned
                .retain(|&(j, t), _| j != id || tiles.binary_search(&t).is_err());
        }
        if !forget.is_empty() {
            sh.persistence.write(Write::ForgetTiles {
                job: id,
                tiles: forget.clone(),
            });
        }
        info!(job = id, tiles = ?tiles, "tiles requeued by an operator");
        self.log(
            sh,
            id,
            "requeued",
            format!(
                "tiles {tiles:?} from {peer} ({} of them done before)",
                forget.len()
            ),
        );
        self.tiles_event(sh, Event::RequeueTiles { job: id, tiles });
        Ok(controls)
    }

    /// A client's view of a job.
    /// None for an unknown job, and for a studio view's pass: clients and the status
    /// page see only the jobs that are kept.
    pub fn status(&self, id: JobId) -> Option<JobStatus> {
        if self.sequences.contains_key(&id) {
            return self.sequence_status(id);
        }
        let job = self.farm.lifecycle().job(id)?;
        let record = self.jobs.get(&id).filter(|r| !r.interactive)?;
        let pass_rung = self.farm.pass_run(id).map(|r| r.rung());
        let mut status = record.status(id, job, pass_rung, self.now.unix_ms);
        if let Some(on) = self.farm.dependencies().waiting_for(id) {
            // Not for want of a worker: no tile of it goes out before these are done.
            status.state = JobState::Waiting;
            status.waiting_for = on.iter().copied().collect();
        } else if !status.state.is_final() {
            status.warning = self
                .no_worker_warning()
                .or_else(|| self.pool_warning(&record.require, record.verification));
        }
        Some(status)
    }

    /// The connected worker an operator names: by id (as `tessera workers` lists
    /// them), or by name (unique among connected workers, [`names`]). `Err` is the
    /// one-line reason none is.
    fn named_worker(&self, key: &str) -> Result<WorkerId, Refusal> {
        if let Ok(id) = key.parse::<WorkerId>() {
            if self.workers.contains_key(&id) {
                return Ok(id);
            }
        }
        self.workers
            .iter()
            .find(|(_, w)| w.name == key)
            .map(|(&id, _)| id)
            .ok_or_else(|| {
                Refusal::not_found(format!(
                    "no worker {key:?} is connected: give an id or a name from tessera workers"
                ))
            })
    }

    /// An operator drains a worker: it is told to finish what it holds and exit (as
    /// on SIGTERM), and gets no new tile from now on. Returns its id.
    pub fn drain_worker(&mut self, sh: &Arc<Shared>, key: &str) -> Result<WorkerId, Refusal> {
        let worker = self.named_worker(key)?;
        let mut newly = false;
        if let Some(w) = self.workers.get_mut(&worker) {
            info!(worker, name = %w.name, host = %w.host, "worker drained by an operator");
            newly = !w.draining;
            w.draining = true;
            let _ = w.outbox.send(ToWorker::Drain);
        }
        if newly {
            self.announce_worker(sh, worker, "drained", serde_json::json!({}));
        }
        self.tiles_event(sh, Event::WorkerDraining { worker });
        Ok(worker)
    }

    /// An operator disables (`true`) or enables a machine, named by a connected
    /// worker's id or name, or (to enable) by the name of a disabled machine not
    /// connected now. Returns the machine's name, to be stored before the change is
    /// acknowledged.
    pub fn set_disabled(
        &mut self,
        sh: &Arc<Shared>,
        key: &str,
        disabled: bool,
    ) -> Result<String, Refusal> {
        let machine = match self.named_worker(key) {
            Ok(worker) => self.workers[&worker].name.clone(),
            Err(_) if !disabled && self.farm.tiles().is_disabled(key) => key.to_string(),
            Err(message) => return Err(message),
        };
        if self.farm.tiles().is_disabled(&machine) != disabled {
            let verb = if disabled { "disabled" } else { "enabled" };
            info!(%machine, "machine {verb} by an operator");
            self.announce_machine(sh, &machine, verb, serde_json::json!({}));
            let event = if disabled {
                Event::DisableMachine {
                    machine: machine.clone(),
                }
            } else {
                Event::EnableMachine {
                    machine: machine.clone(),
                }
            };
            self.tiles_event(sh, event);
        }
        Ok(machine)
    }
}

/// Why a job that has ended (`state`) cannot be `verb` (paused, resumed, ...): what
/// would be accepted instead, and for a failed or cancelled job the command that puts
/// it back in the queue, since resuming it is the usual mistake.
pub(super) fn ended_refusal(id: JobId, verb: &str, state: JobState) -> Refusal {
    let accepted = if verb == "resumed" {
        "only a paused job can be"
    } else {
        "only a queued or running job can be"
    };
    let mut refusal = format!(
        "job {id} cannot be {verb}: it is {}, {accepted}",
        state.as_str()
    );
    if matches!(state, JobState::Failed | JobState::Cancelled) {
        refusal.push_str(&format!(
            " (`tessera retry {id}` puts it back in the queue)"
        ));
    }
    Refusal::state(refusal)
}
