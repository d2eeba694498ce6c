//! The job lifecycle: admission, Queued → Running → Done, Failed or Cancelled, when each
//! change is stored, and when a failure is final.
//!
//! A pure state machine like [`crate::tiles`]: the daemon reports what happened
//! ([`Event`], with the time) and carries out the [`Action`]s. It decides:
//!
//! - **Admission.** A submission is checked against the [`Limits`] and the state of the
//!   storage *before* anything is written: a job is refused while the coordinator cannot
//!   store it, and a client may have at most [`Limits::max_active_per_client`] jobs
//!   queued or running (jobs being stored count). An admitted job gets the next id,
//!   which is never given twice (the daemon records the highest id issued durably
//!   beside the database).
//! - **Durable before acknowledged.** An admitted job is `Storing` until the daemon
//!   reports its row written ([`Event::Stored`]); only then is the client told its id
//!   and the tiles handed to the tile scheduler. A failed write releases the id's slot
//!   and the client is told why; the id itself is not reused.
//! - **Final means durable.** When the tiles are all in, the image is stored
//!   ([`Action::StoreImage`]); a job is `Done` for clients only once the image *and* the
//!   final state are written. A failure to store is not a failure of the job: the store
//!   is retried (at [`Limits::retry_ms`]) until the disk is usable again. A job is
//!   `Failed` only for reasons that are final (its tiles failed), and that too becomes
//!   visible once written. Cancelling is final at once for the farm (its tiles are
//!   withdrawn) and written like the others.
//! - **Retention.** A job that ended is deleted (its files and rows) `retention` after
//!   it ended, or when a client asks ([`Event::Delete`]); only ended jobs may be deleted.

use std::collections::{BTreeMap, BTreeSet};
use std::net::IpAddr;

use protocol::{JobId, JobState, Refusal};

use crate::Millis;

/// What a job may ask for, and how the lifecycle is timed. Each bound keeps one client
/// from taking the farm's memory or time from everyone else; exceeding one is a clear
/// error at submission. The defaults are in brackets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Bytes of scene text (8 MiB).
    pub max_scene_bytes: usize,
    /// Objects in a scene (100,000).
    pub max_objects: usize,
    /// Pixels of an image (8192 × 8192 = 67,108,864: 192 MiB of RGB being assembled).
    pub max_pixels: u64,
    /// Antialiasing (16: 256 samples per pixel). It bounds the budget of every sampler
    /// too: adaptive sampling may spend all of it on a pixel.
    pub max_aa: u32,
    /// Jobs queued, running or being stored per client address (64).
    pub max_active_per_client: usize,
    /// Pixels of all the jobs queued, running or being stored: what bounds the memory
    /// of the frames being assembled (3 bytes a pixel).
    pub max_active_pixels: u64,
    /// An ended job is deleted this long after it ended (`None`: kept until deleted).
    pub retention: Option<Millis>,
    /// How long after a failed store of an image it is tried again.
    pub retry_ms: Millis,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_scene_bytes: 8 * 1024 * 1024,
            max_objects: 100_000,
            max_pixels: 8192 * 8192,
            max_aa: 16,
            max_active_per_client: 64,
            // Four of the largest frames: 768 MiB of frames being assembled at most.
            max_active_pixels: 4 * 8192 * 8192,
            retention: None,
            retry_ms: 500,
        }
    }
}

impl Limits {
    /// Checks the size of a scene's text (before parsing it, so that an oversized
    /// scene costs nothing).
    pub fn check_scene_bytes(&self, bytes: usize) -> Result<(), Refusal> {
        if bytes > self.max_scene_bytes {
            return Err(Refusal::invalid(format!(
                "the scene is {bytes} bytes, more than this coordinator's limit of {}",
                self.max_scene_bytes
            )));
        }
        Ok(())
    }

    /// Checks a submission against every bound; the error is the one-line message for
    /// the client.
    pub fn check(&self, request: &Request) -> Result<(), Refusal> {
        self.check_scene_bytes(request.scene_bytes)?;
        if request.objects > self.max_objects {
            return Err(Refusal::invalid(format!(
                "objects: {} objects, more than this coordinator's limit of {}",
                request.objects, self.max_objects
            )));
        }
        let pixels = u64::from(request.width) * u64::from(request.height);
        if pixels > self.max_pixels {
            return Err(Refusal::invalid(format!(
                "image: {}x{} is {pixels} pixels, more than this coordinator's limit of {}",
                request.width, request.height, self.max_pixels
            )));
        }
        if request.aa > self.max_aa {
            return Err(Refusal::invalid(format!(
                "image.aa: {} is more than this coordinator's limit of {}",
                request.aa, self.max_aa
            )));
        }
        Ok(())
    }
}

/// What a submission asks for, as the daemon measured it (it parses the scene outside
/// any lock; the lifecycle only compares numbers).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Request {
    pub client: Option<IpAddr>,
    pub scene_bytes: usize,
    pub objects: usize,
    pub width: u32,
    pub height: u32,
    pub aa: u32,
}

/// Where a job stands, as the lifecycle sees it (finer than [`JobState`], which is what
/// clients see).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Admitted, its row being written; not yet acknowledged.
    Storing,
    /// Stored, no tile handed out yet.
    Queued,
    /// Tiles handed out.
    Running,
    /// Every tile is in; the image is being stored (again after a failure, at `retry_at`).
    Finishing { retry_at: Option<Millis> },
    /// The job ended as `state`; `recorded` once the state is written.
    Ended {
        state: JobState,
        error: Option<String>,
        recorded: bool,
    },
}

impl Phase {
    /// What clients are told. A job whose end is not yet written still shows running.
    pub fn visible(&self) -> JobState {
        match self {
            Phase::Storing | Phase::Queued => JobState::Queued,
            Phase::Running | Phase::Finishing { .. } => JobState::Running,
            Phase::Ended {
                recorded: false,
                state: JobState::Cancelled,
                ..
            } => JobState::Cancelled,
            Phase::Ended {
                recorded: false, ..
            } => JobState::Running,
            Phase::Ended { state, .. } => *state,
        }
    }

    /// Whether the job no longer needs the farm.
    pub fn has_ended(&self) -> bool {
        matches!(self, Phase::Ended { .. })
    }
}

/// One job's lifecycle.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Job {
    pub phase: Phase,
    pub client: Option<IpAddr>,
    /// The image's pixels (what its frame costs while it is active).
    pub pixels: u64,
    /// When the job ended (the lifecycle's clock), which its retention runs from. The
    /// wall-clock times shown to users are the daemon's to keep.
    pub ended: Option<Millis>,
}

/// Something that happened to jobs.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// The job's row is written: acknowledge it and hand its tiles out.
    Stored {
        job: JobId,
    },
    /// The job's row could not be written.
    StoreFailed {
        job: JobId,
        message: String,
    },
    /// A job found in the database at startup, with the state it had.
    Restored {
        job: JobId,
        state: JobState,
        error: Option<String>,
        /// Whether some of its tiles are done (it had started).
        started: bool,
        /// The image's pixels.
        pixels: u64,
        /// For a job that had ended: how long before the restart it ended (its
        /// retention runs from its end, not from the restart).
        ended_ago: Millis,
    },
    /// The tile scheduler handed out a tile of the job.
    TileAssigned {
        job: JobId,
    },
    /// The tile scheduler has every tile of the job.
    TilesComplete {
        job: JobId,
    },
    /// The tile scheduler gave up on the job (final).
    TilesFailed {
        job: JobId,
        message: String,
    },
    /// The image was stored (`Ok`) or could not be (`Err`, transient).
    ImageStored {
        job: JobId,
        result: Result<(), String>,
    },
    /// The final state of the job is written.
    EndRecorded {
        job: JobId,
    },
    /// A client cancels the job.
    Cancel {
        job: JobId,
    },
    /// A client deletes the job.
    Delete {
        job: JobId,
    },
    /// The job's files and rows are gone.
    Deleted {
        job: JobId,
    },
    /// Storage cannot write now / can again.
    StorageUnavailable {
        reason: String,
    },
    StorageAvailable,
    /// The time has come (see [`Lifecycle::next_deadline`]).
    Timeout,
    /// An operator puts a failed or cancelled job back in the queue, its stored
    /// tiles (`started`: some) counting ([`Lifecycle::check_retry`] says whether it
    /// may be). Its retention stops: it is active again, with its image's `pixels`.
    Retry {
        job: JobId,
        started: bool,
        pixels: u64,
    },
}

/// What the daemon must do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Action {
    /// Tell the client its job is accepted, and give its tiles to the tile scheduler.
    Acknowledge { job: JobId },
    /// Tell the client the job could not be stored.
    RefuseStored { job: JobId, message: String },
    /// Assemble, encode and store the image, then report [`Event::ImageStored`].
    StoreImage { job: JobId },
    /// Withdraw the job's tiles from the tile scheduler.
    CancelTiles { job: JobId },
    /// Write the job's final state, then report [`Event::EndRecorded`].
    RecordEnd {
        job: JobId,
        state: JobState,
        error: Option<String>,
    },
    /// Remove the job's files and rows, then report [`Event::Deleted`].
    DeleteStored { job: JobId },
    /// Reply to a client's request on a job.
    Reply {
        job: JobId,
        result: Result<Reply, Refusal>,
    },
}

/// A successful answer to a client's request on a job.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reply {
    Cancelled,
    Deleting,
    Retried,
}

/// Every job's lifecycle.
#[derive(Clone, Debug, Default)]
pub struct Lifecycle {
    limits: Limits,
    now: Millis,
    jobs: BTreeMap<JobId, Job>,
    /// The next id to give: above every id ever issued.
    next_id: JobId,
    /// Why storage cannot write, while it cannot.
    storage_down: Option<String>,
    /// Ended jobs by the time they are to be deleted.
    expiry: BTreeSet<(Millis, JobId)>,
    /// Jobs being deleted.
    deleting: BTreeSet<JobId>,
    /// Jobs that never expire on their own: the frame jobs of a sequence, which the
    /// sequence's own retention deletes with it.
    kept: BTreeSet<JobId>,
}

impl Lifecycle {
    /// A lifecycle whose next job id is `next_id` (above every id ever issued).
    pub fn new(limits: Limits, next_id: JobId) -> Self {
        Lifecycle {
            limits,
            next_id: next_id.max(1),
            ..Self::default()
        }
    }

    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    pub fn job(&self, job: JobId) -> Option<&Job> {
        self.jobs.get(&job)
    }

    pub fn jobs(&self) -> impl DoubleEndedIterator<Item = (JobId, &Job)> {
        self.jobs.iter().map(|(&id, j)| (id, j))
    }

    /// The id the next admitted job will get.
    pub fn next_id(&self) -> JobId {
        self.next_id
    }

    /// Why storage cannot write, while it cannot.
    pub fn storage_down(&self) -> Option<&str> {
        self.storage_down.as_deref()
    }

    /// Checks a submission and, if it may be stored, gives it an id and enters it as
    /// [`Phase::Storing`]. The error is the one-line message for the client.
    pub fn admit(&mut self, now: Millis, request: &Request) -> Result<JobId, Refusal> {
        self.now = self.now.max(now);
        let limits = &self.limits;
        if let Some(reason) = &self.storage_down {
            return Err(Refusal::unavailable(format!(
                "the coordinator cannot store new jobs now (storage unavailable: {reason}): \
                 submit again later"
            )));
        }
        limits.check(request)?;
        if let Some(client) = request.client {
            let active = self
                .jobs
                .values()
                .filter(|j| j.client == Some(client) && !j.phase.has_ended())
                .count();
            if active >= limits.max_active_per_client {
                return Err(Refusal::limit(format!(
                    "{client} already has {active} jobs queued or running, this coordinator's \
                     limit: wait for some to finish"
                )));
            }
        }
        let pixels = u64::from(request.width) * u64::from(request.height);
        let active: u64 = self
            .jobs
            .values()
            .filter(|j| !j.phase.has_ended())
            .map(|j| j.pixels)
            .sum();
        if active.saturating_add(pixels) > limits.max_active_pixels {
            return Err(Refusal::limit(format!(
                "the coordinator has jobs of {active} pixels queued or running; this one's \
                 {pixels} would pass its limit of {}: submit again when some have finished",
                limits.max_active_pixels
            )));
        }
        let id = self.next_id;
        self.next_id += 1;
        self.jobs.insert(
            id,
            Job {
                phase: Phase::Storing,
                client: request.client,
                pixels,
                ended: None,
            },
        );
        Ok(id)
    }

    /// Issues an id that is not a job of the lifecycle's own: a sequence job's (its
    /// frames are jobs). Ids are never issued twice either way.
    pub fn issue_id(&mut self) -> JobId {
        let id = self.next_id;
        self.next_id += 1;
        id
    }

    /// The job never expires on its own (a sequence's frame job: it is deleted with
    /// its sequence).
    pub fn keep(&mut self, job: JobId) {
        self.kept.insert(job);
        self.expiry.retain(|&(_, j)| j != job);
    }

    /// The earliest time at which [`Event::Timeout`] has something to do.
    pub fn next_deadline(&self) -> Option<Millis> {
        let retry = self
            .jobs
            .values()
            .filter_map(|j| match j.phase {
                Phase::Finishing { retry_at } => retry_at,
                _ => None,
            })
            .min();
        let expiry = self.expiry.first().map(|&(at, _)| at);
        retry.into_iter().chain(expiry).min()
    }

    /// Applies one event at time `now` and returns what to do, in order.
    pub fn handle(&mut self, now: Millis, event: Event) -> Vec<Action> {
        self.now = self.now.max(now);
        let now = self.now;
        let mut actions = Vec::new();
        match event {
            Event::Stored { job } => {
                if let Some(j) = self.jobs.get_mut(&job) {
                    if j.phase == Phase::Storing {
                        j.phase = Phase::Queued;
                        actions.push(Action::Acknowledge { job });
                    }
                }
            }
            Event::StoreFailed { job, message } => {
                if self
                    .jobs
                    .get(&job)
                    .is_some_and(|j| j.phase == Phase::Storing)
                {
                    self.jobs.remove(&job);
                    actions.push(Action::RefuseStored { job, message });
                }
            }
            Event::Restored {
                job,
                state,
                error,
                started,
                pixels,
                ended_ago,
            } => {
                self.next_id = self.next_id.max(job + 1);
                let phase = if state.is_final() {
                    Phase::Ended {
                        state,
                        error,
                        recorded: true,
                    }
                } else if started {
                    Phase::Running
                } else {
                    Phase::Queued
                };
                let ended = phase.has_ended().then_some(now);
                self.jobs.insert(
                    job,
                    Job {
                        phase,
                        client: None,
                        pixels,
                        ended,
                    },
                );
                if ended.is_some() && !self.kept.contains(&job) {
                    if let Some(keep) = self.limits.retention {
                        let at = (now + keep).saturating_sub(ended_ago);
                        self.expiry.insert((at, job));
                    }
                }
            }
            Event::TileAssigned { job } => {
                if let Some(j) = self.jobs.get_mut(&job) {
                    if j.phase == Phase::Queued {
                        j.phase = Phase::Running;
                    }
                }
            }
            Event::TilesComplete { job } => {
                if let Some(j) = self.jobs.get_mut(&job) {
                    if matches!(j.phase, Phase::Queued | Phase::Running) {
                        j.phase = Phase::Finishing { retry_at: None };
                        actions.push(Action::StoreImage { job });
                    }
                }
            }
            Event::TilesFailed { job, message } => {
                self.end(job, JobState::Failed, Some(message), &mut actions);
            }
            Event::ImageStored { job, result } => {
                let retry = self.limits.retry_ms;
                if let Some(j) = self.jobs.get_mut(&job) {
                    if matches!(j.phase, Phase::Finishing { .. }) {
                        match result {
                            Ok(()) => self.end(job, JobState::Done, None, &mut actions),
                            Err(_) => {
                                j.phase = Phase::Finishing {
                                    retry_at: Some(now + retry),
                                }
                            }
                        }
                    }
                }
            }
            Event::EndRecorded { job } => {
                if let Some(j) = self.jobs.get_mut(&job) {
                    if let Phase::Ended { recorded, .. } = &mut j.phase {
                        if !*recorded {
                            *recorded = true;
                            if self.deleting.contains(&job) {
                                // Deleted while its end was being written.
                                actions.push(Action::DeleteStored { job });
                            } else {
                                // Retention counts from the end; only a written end
                                // expires.
                                let ended = j.ended.unwrap_or(now);
                                self.schedule_expiry(job, ended);
                            }
                        }
                    }
                }
            }
            Event::Cancel { job } => {
                let result = match self.jobs.get(&job).map(|j| &j.phase) {
                    None | Some(Phase::Storing) => Err(unknown(job)),
                    Some(Phase::Ended { state, .. }) => Err(Refusal::state(format!(
                        "job {job} is already {}",
                        state.as_str()
                    ))),
                    Some(_) => {
                        actions.push(Action::CancelTiles { job });
                        self.end(job, JobState::Cancelled, None, &mut actions);
                        Ok(Reply::Cancelled)
                    }
                };
                actions.push(Action::Reply { job, result });
            }
            Event::Delete { job } => {
                let result = match self.jobs.get(&job).map(|j| &j.phase) {
                    None | Some(Phase::Storing) => Err(unknown(job)),
                    Some(Phase::Ended { recorded: true, .. }) => {
                        if self.deleting.insert(job) {
                            actions.push(Action::DeleteStored { job });
                        }
                        Ok(Reply::Deleting)
                    }
                    // Ended (a cancel answered a moment ago) but its end not yet
                    // written: deleted once it is, so that a file written later does
                    // not bring it back.
                    Some(Phase::Ended {
                        recorded: false, ..
                    }) => {
                        self.deleting.insert(job);
                        Ok(Reply::Deleting)
                    }
                    Some(phase) => Err(Refusal::state(format!(
                        "job {job} is {}: cancel it first",
                        phase.visible().as_str()
                    ))),
                };
                actions.push(Action::Reply { job, result });
            }
            Event::Retry {
                job,
                started,
                pixels,
            } => {
                let result = self.check_retry(job, pixels).map(|()| {
                    if let Some(j) = self.jobs.get_mut(&job) {
                        j.phase = if started {
                            Phase::Running
                        } else {
                            Phase::Queued
                        };
                        j.ended = None;
                        j.pixels = pixels;
                    }
                    self.expiry.retain(|&(_, j)| j != job);
                    Reply::Retried
                });
                actions.push(Action::Reply { job, result });
            }
            Event::Deleted { job } => {
                self.deleting.remove(&job);
                self.kept.remove(&job);
                if self.jobs.remove(&job).is_some() {
                    // Deletions are rare: a walk of the expiry list costs nothing much.
                    self.expiry.retain(|&(_, j)| j != job);
                }
            }
            Event::StorageUnavailable { reason } => self.storage_down = Some(reason),
            Event::StorageAvailable => {
                self.storage_down = None;
                // Images waiting for a retry are stored at once.
                for (&job, j) in &mut self.jobs {
                    if let Phase::Finishing { retry_at } = &mut j.phase {
                        if retry_at.take().is_some() {
                            actions.push(Action::StoreImage { job });
                        }
                    }
                }
            }
            Event::Timeout => {
                for (&job, j) in &mut self.jobs {
                    if let Phase::Finishing { retry_at } = &mut j.phase {
                        if retry_at.is_some_and(|at| at <= now) {
                            *retry_at = None;
                            actions.push(Action::StoreImage { job });
                        }
                    }
                }
                while let Some(&(at, job)) = self.expiry.first() {
                    if at > now {
                        break;
                    }
                    self.expiry.pop_first();
                    if self.deleting.insert(job) {
                        actions.push(Action::DeleteStored { job });
                    }
                }
            }
        }
        actions
    }

    /// Ends an active job as `state` and has the end written.
    fn end(
        &mut self,
        job: JobId,
        state: JobState,
        error: Option<String>,
        actions: &mut Vec<Action>,
    ) {
        let now = self.now;
        let Some(j) = self.jobs.get_mut(&job) else {
            return;
        };
        if j.phase.has_ended() || j.phase == Phase::Storing {
            return;
        }
        j.phase = Phase::Ended {
            state,
            error: error.clone(),
            recorded: false,
        };
        j.ended = Some(now);
        actions.push(Action::RecordEnd { job, state, error });
    }

    fn schedule_expiry(&mut self, job: JobId, ended: Millis) {
        if self.kept.contains(&job) {
            return;
        }
        if let Some(keep) = self.limits.retention {
            self.expiry.insert((ended + keep, job));
        }
    }
}

impl Lifecycle {
    /// Whether the job may go back to the queue: only a job that failed or was
    /// cancelled, its end recorded, and not being deleted. A job that is done is not
    /// retried: its image is final and stored (submit the scene again to render it
    /// anew). Like a submission, it must fit in the pixels of the active jobs, and
    /// storage must be able to write.
    pub fn check_retry(&self, job: JobId, pixels: u64) -> Result<(), Refusal> {
        self.check_retry_state(job)?;
        if let Some(reason) = &self.storage_down {
            return Err(Refusal::unavailable(format!(
                "job {job} cannot be retried now (storage unavailable: {reason}): retry later"
            )));
        }
        let active: u64 = self
            .jobs
            .values()
            .filter(|j| !j.phase.has_ended())
            .map(|j| j.pixels)
            .sum();
        if active.saturating_add(pixels) > self.limits.max_active_pixels {
            return Err(Refusal::limit(format!(
                "job {job} cannot be retried now: the coordinator has jobs of {active} pixels \
                 queued or running, and its {pixels} would pass its limit of {}",
                self.limits.max_active_pixels
            )));
        }
        Ok(())
    }

    fn check_retry_state(&self, job: JobId) -> Result<(), Refusal> {
        match self.jobs.get(&job).map(|j| &j.phase) {
            None | Some(Phase::Storing) => Err(unknown(job)),
            Some(_) if self.deleting.contains(&job) => Err(Refusal::state(format!(
                "job {job} cannot be retried: it is being deleted"
            ))),
            Some(Phase::Ended {
                state: JobState::Failed | JobState::Cancelled,
                recorded: true,
                ..
            }) => Ok(()),
            Some(Phase::Ended {
                state: JobState::Done,
                ..
            }) => Err(Refusal::state(format!(
                "job {job} cannot be retried: it is done and its image is final (submit \
                 the scene again to render it anew)"
            ))),
            Some(Phase::Ended { .. }) => Err(Refusal::state(format!(
                "job {job} cannot be retried yet: its end is still being stored"
            ))),
            Some(phase) => Err(Refusal::state(format!(
                "job {job} cannot be retried: it is {}, only a failed or cancelled job can be",
                phase.visible().as_str()
            ))),
        }
    }
}

fn unknown(job: JobId) -> Refusal {
    Refusal::unknown_job(job)
}

#[cfg(test)]
mod retry_limit_tests;
#[cfg(test)]
mod retry_tests;
#[cfg(test)]
mod tests;
