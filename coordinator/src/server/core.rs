//! The state behind the daemon's one lock: the decision core ([`Farm`]), the data its
//! decisions are about (scenes, frames being assembled, workers' outboxes), and how
//! its effects are carried out.
//!
//! Everything here runs under the lock, so nothing here blocks: messages go to
//! per-worker channels, writes to the persistence queue, and encoding an image to the
//! blocking pool.
//!
//! Every part is a set of methods of [`Core`]: jobs entering it ([`admission`]), its
//! effects carried out ([`effects`]), a worker's results ([`results`]) and a lying
//! machine's quarantine ([`quarantine`]), an adaptive job's passes ([`passes`]),
//! operators' controls ([`controls`]), workers ([`workers`]) and sequence jobs
//! ([`sequences`]); what they keep is in [`records`]. This module holds the core
//! itself, how an input is fed to it and its effects dispatched, and what every part
//! uses: storing a write, logging a job's event.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use protocol::{ClientResponse, JobEvent, JobId, Refusal, WorkerId};
use scheduler::farm::{Effect, Farm, Input, TilePlan};
use scheduler::lifecycle::{self, Lifecycle, Phase, Reply};
use scheduler::{Event, Millis, Scheduler};
use tokio::sync::oneshot;
use tracing::{error, info};

use super::persistence::Write;
use super::Shared;
use crate::db::EventWrite;

mod admission;
mod controls;
mod effects;
mod figures;
mod names;
mod passes;
mod pools;
mod quarantine;
mod records;
mod results;
mod sequences;
mod workers;

pub use records::{Controls, Cost, Dropped, Prepared, TilePixels, WorkerRecord};
use records::{Held, JobRecord, EVENT_LOG_CAP};
pub use results::Verdict;
pub(super) use sequences::frame_jobs;
pub use sequences::SequenceRecord;

/// The decision core and its data.
pub struct Core {
    /// The daemon's clocks as the lock was taken (`Shared::lock`): everything decided
    /// under the lock sees this one time, and the core reads no clock of its own.
    pub now: Now,
    pub farm: Farm,
    /// Inputs that arose while effects were being carried out, fed once they all are:
    /// the effects before them reach the world first, in the order the core made them.
    deferred: VecDeque<Input>,
    pub jobs: BTreeMap<JobId, JobRecord>,
    /// Sequence jobs, whose frames are jobs of `jobs`.
    pub sequences: BTreeMap<JobId, SequenceRecord>,
    pub workers: BTreeMap<WorkerId, WorkerRecord>,
    next_worker: WorkerId,
    /// Clients waiting for their submission to be stored.
    submits: HashMap<JobId, oneshot::Sender<ClientResponse>>,
    /// Results held until another machine confirms them, by job and tile.
    held: HashMap<(JobId, u32), Held>,
    /// Machines caught returning wrong pixels, with why: they get no tile again.
    pub quarantined: BTreeMap<String, String>,
    /// The scheduler's count of expired leases when last looked at, and the expired
    /// leases already in the jobs' event logs.
    leases_expired_seen: u64,
    expiries_logged: HashSet<(JobId, u32, WorkerId)>,
    /// Rendering time of every result accepted since the start: the pace a job's
    /// waiting work is estimated at before its own first result ([`pools`]).
    measured: pools::Measured,
}

/// The daemon's clocks at one moment, passed in to the core: the decision core's
/// milliseconds, the same instant for round trips and rates, and the wall clock for
/// the times stored and shown.
#[derive(Clone, Copy, Debug)]
pub struct Now {
    /// Milliseconds on the daemon's monotonic clock, since `epoch`.
    pub mono: Millis,
    pub instant: Instant,
    /// Milliseconds since the Unix epoch.
    pub unix_ms: u64,
}

impl Core {
    /// A core whose clocks read `now` until the lock is first taken.
    pub fn new(tiles: Scheduler, lifecycle: Lifecycle, now: Now) -> Core {
        Core {
            now,
            farm: Farm::new(tiles, lifecycle),
            deferred: VecDeque::new(),
            jobs: BTreeMap::new(),
            workers: BTreeMap::new(),
            next_worker: 1,
            submits: HashMap::new(),
            held: HashMap::new(),
            quarantined: BTreeMap::new(),
            leases_expired_seen: 0,
            expiries_logged: HashSet::new(),
            sequences: BTreeMap::new(),
            measured: pools::Measured::default(),
        }
    }

    /// The earliest deadline of either state machine.
    pub fn next_deadline(&self, now: Millis) -> Option<Millis> {
        // A sequence is deleted when its retention runs out.
        let expiry = self.next_sequence_expiry().map(|ms| now + ms);
        [self.farm.next_deadline(), expiry]
            .into_iter()
            .flatten()
            .min()
    }

    /// The time has come: the core looks at its deadlines.
    pub fn timeout(&mut self, sh: &Arc<Shared>) {
        for job in sh.studio.tick(self.now.mono) {
            self.life_event(sh, lifecycle::Event::Cancel { job });
        }
        self.feed(sh, Input::Timeout);
        self.log_expired_leases(sh);
        self.expire_sequences(sh);
    }

    /// The core goes on with what its last call left at a bound (a hand-out, checks):
    /// leases it ran out meanwhile reach the jobs' event logs.
    pub fn go_on(&mut self, sh: &Arc<Shared>) {
        let expired = self.farm.tiles().counters().leases_expired;
        self.tiles_event(sh, Event::Continue);
        if self.farm.tiles().counters().leases_expired != expired {
            self.log_expired_leases(sh);
        }
    }

    /// Whether tiles are out or images are being stored (a shutdown waits for them).
    pub fn is_busy(&self) -> bool {
        self.farm.tiles().tiles_in_flight() > 0
            || self
                .farm
                .lifecycle()
                .jobs()
                .any(|(_, j)| matches!(j.phase, Phase::Finishing { .. }))
    }

    /// Every worker finishes what it holds and gets nothing more.
    pub fn drain_all(&mut self, sh: &Arc<Shared>) {
        let workers: Vec<WorkerId> = self.workers.keys().copied().collect();
        for worker in workers {
            self.tiles_event(sh, Event::WorkerDraining { worker });
        }
    }

    /// Hands a write about `job` to the disk, or, for a job nothing is kept of (a
    /// studio view's pass), discards it on the blocking pool, where its callback runs
    /// as if it had been stored: never under the lock the caller holds.
    pub fn store(&self, sh: &Shared, job: JobId, write: Write) {
        if self.jobs.get(&job).is_some_and(|r| r.interactive) {
            drop(sh.runtime.spawn_blocking(move || write.discard()));
        } else {
            sh.persistence.write(write);
        }
    }

    /// Adds an entry to the job's event log (queued for the disk, never waited for),
    /// and announces it on the farm's stream when its kind is one of the stream's.
    /// `kind` is one of the words docs/operations.md lists. A studio view's pass keeps
    /// no log.
    pub fn log(&mut self, sh: &Shared, job: JobId, kind: &str, detail: String) {
        // The farm's stream tells of it too, whether or not the job's log still keeps
        // entries.
        self.announce_logged(sh, job, kind, &detail);
        let log = match (self.jobs.get_mut(&job), self.sequences.get_mut(&job)) {
            (Some(record), _) if !record.interactive => &mut record.log,
            (None, Some(sequence)) => &mut sequence.log,
            _ => return,
        };
        let end = matches!(kind, "done" | "failed" | "cancelled");
        let unix_ms = self.now.unix_ms;
        let (seq, kind, detail) = match log.number(end) {
            Some(seq) => (seq, kind.to_owned(), detail),
            None => (
                EVENT_LOG_CAP + 1,
                "not_kept".to_owned(),
                format!("{} further events not kept", log.dropped),
            ),
        };
        sh.persistence.write(Write::Event(EventWrite {
            job,
            event: JobEvent {
                seq,
                unix_ms,
                kind,
                detail,
            },
        }));
    }

    /// Feeds the core an input about tiles and workers, and carries out its effects.
    pub fn tiles_event(&mut self, sh: &Arc<Shared>, event: Event) {
        self.feed(sh, Input::Tiles(event));
    }

    /// Feeds the core an input about jobs and carries out its effects; returns the
    /// reply to the client that caused it, for the inputs that ask for one (cancel,
    /// delete, retry), and `None` for a job the core does not know.
    pub fn life_event(
        &mut self,
        sh: &Arc<Shared>,
        event: lifecycle::Event,
    ) -> Option<Result<Reply, Refusal>> {
        self.feed(sh, Input::Job(event))
    }

    /// Feeds the core one input at the daemon's clock and carries out its effects,
    /// then the inputs they deferred.
    fn feed(&mut self, sh: &Arc<Shared>, input: Input) -> Option<Result<Reply, Refusal>> {
        let effects = self.farm.handle(self.now.mono, input);
        self.carry_out(sh, effects)
    }

    /// Carries out effects, then feeds the inputs they deferred.
    fn carry_out(
        &mut self,
        sh: &Arc<Shared>,
        effects: Vec<Effect>,
    ) -> Option<Result<Reply, Refusal>> {
        let reply = self.apply(sh, effects);
        while let Some(input) = self.deferred.pop_front() {
            let effects = self.farm.handle(self.now.mono, input);
            self.apply(sh, effects);
        }
        reply
    }

    /// Carries out the core's effects in order; returns the reply to a client's
    /// request among them (one input asks for one at most).
    fn apply(&mut self, sh: &Arc<Shared>, effects: Vec<Effect>) -> Option<Result<Reply, Refusal>> {
        let mut reply = None;
        for effect in effects {
            match effect {
                Effect::Tiles(action) => self.apply_tiles(sh, action),
                Effect::Pass(action) => self.apply_pass(sh, action),
                Effect::Sequence(action) => self.apply_sequence(sh, action),
                Effect::TakenBack { job, tiles } => self.taken_back(sh, job, tiles),
                Effect::Quarantined {
                    machine,
                    caught_in,
                    reason,
                    taken,
                } => self.quarantined(sh, &machine, caught_in, &reason, &taken),
                Effect::DuplicateSettled {
                    job,
                    tile,
                    machine,
                    same,
                } => {
                    if same {
                        info!(
                            machine,
                            job, tile, "duplicate result equals the accepted one"
                        );
                    } else {
                        error!(
                            machine,
                            job, tile, "duplicate result differs from the accepted one"
                        );
                    }
                }
                Effect::Waiting { job, on } => {
                    let on: Vec<String> = on.iter().map(|j| format!("job {j}")).collect();
                    info!(job, on = %on.join(", "), "job waits for the jobs it was submitted after");
                    self.log(
                        sh,
                        job,
                        "waiting",
                        format!("for {} to be done", on.join(", ")),
                    );
                }
                Effect::Released { job } => {
                    info!(job, "the jobs it waits for are done: its tiles go out");
                    self.log(sh, job, "released", "the jobs it waits for are done".into());
                }
                Effect::Job(action) => {
                    if let Some(answer) = self.apply_life(sh, action) {
                        debug_assert!(reply.is_none(), "two replies to one input");
                        reply = Some(answer);
                    }
                }
            }
        }
        sh.changed();
        reply
    }

    /// How the job's tiles go out, from its record.
    fn plan_of(record: &JobRecord) -> TilePlan {
        TilePlan {
            priority: record.priority,
            scene: record.hash,
            tiles: record.tiles_total,
            interactive: record.interactive,
        }
    }

    /// Tiles are durably recorded: they count in the progress reported.
    pub fn tiles_recorded(&mut self, tiles: &[(JobId, u32)]) {
        for (job, _) in tiles {
            if let Some(record) = self.jobs.get_mut(job) {
                record.tiles_recorded = (record.tiles_recorded + 1).min(record.tiles_total);
            }
        }
    }

    /// Storage became unavailable or available again.
    pub fn storage(&mut self, sh: &Arc<Shared>, status: Result<(), String>) {
        self.feed(sh, Input::Storage(status));
    }
}

/// The error for a job this coordinator does not know.
fn unknown(id: JobId) -> Refusal {
    Refusal::unknown_job(id)
}

#[cfg(test)]
mod tests;
