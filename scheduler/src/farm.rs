//! The farm's decision core: the tile scheduler and the job lifecycle joined into one
//! state machine, `handle(now, input) -> effects`.
//!
//! Each of the two machines decides alone what it owns (tiles and workers; jobs and
//! what is stored of them), but many of their decisions feed the other: a tile handed
//! out makes a queued job running, a job's last tile makes its image due, a cancelled
//! job's tiles must be withdrawn, a stored job's tiles go out. Those rules live here,
//! once, so that the coordinator daemon and the simulator cannot glue the two
//! differently: both feed [`Input`]s, with the time passed in, and carry out the
//! [`Effect`]s in the order given, each the way its world does (a socket and a disk,
//! or a virtual network and a virtual disk).
//!
//! The rules:
//! - a tile handed out ([`Action::Assign`]) tells the lifecycle
//!   ([`lifecycle::Event::TileAssigned`]);
//! - a job's last tile ([`Action::JobDone`]) makes its image due
//!   ([`lifecycle::Event::TilesComplete`]), except for a job rendered in passes: its
//!   pass is added up ([`PassAction::AddUp`]), and the totals ([`PassInput::Evaluated`])
//!   make the image due or start the next pass, whose tiles go out as a resumed job's,
//!   paused if an operator paused the job (see [`crate::passes`]);
//! - a job in passes whose results are taken back ([`PassInput::TakeBack`]) has its
//!   tiles withdrawn and its pass started again;
//! - a machine caught returning wrong pixels ([`Input::Quarantine`]), or whose copy of
//!   a tile is shown wrong against another ([`Input::Duplicate`]), is quarantined
//!   ([`Effect::Quarantined`]) and has the tiles it rendered in the active jobs taken
//!   back ([`Effect::TakenBack`], for the executor to forget their pixels) and
//!   rendered again by others ([`Event::Quarantine`]): the core keeps which machine
//!   rendered each accepted tile while its job is active;
//! - a job the scheduler gives up ([`Action::JobFailed`]) fails
//!   ([`lifecycle::Event::TilesFailed`]);
//! - a job whose row is written ([`lifecycle::Action::Acknowledge`]) has its tiles
//!   handed out as [`Farm::admit`] described them ([`Event::JobSubmitted`], then
//!   [`Event::Interactive`] for a studio view's pass);
//! - a job that ends early ([`lifecycle::Action::CancelTiles`]) has its tiles
//!   withdrawn ([`Event::CancelJob`]);
//! - a stored job submitted after others waits, its tiles kept back, until every one
//!   of them is done and its end written ([`Effect::Waiting`], then
//!   [`Effect::Released`]); one that fails or is cancelled fails it, naming it (see
//!   [`dependencies`]);
//! - the time ([`Input::Timeout`]) reaches the tile scheduler first, then the
//!   lifecycle; [`Farm::next_deadline`] is the earlier of theirs;
//! - storage that cannot write ([`Input::Storage`]) stops the tile scheduler first
//!   (no tile goes out whose result could not be recorded), then the lifecycle (no
//!   job is admitted); storage that writes again reaches them in the other order.
//!
//! The follow-ups are handled depth first, right after the effect that caused them,
//! as a direct call would: the effects come out in the order the two machines made
//! them.

use std::collections::{BTreeMap, BTreeSet};

use protocol::{JobId, JobState, Refusal, SceneHash, WorkerId};

pub use self::dependencies::Dependencies;
pub use self::disputes::{CopyVerdict, Duplicate};
pub use self::pass_run::{PassAction, PassInput, PassRun, PassTile};
use self::renderers::Renderers;
pub use self::sequence_run::{SequenceAction, SequenceInput, SequenceRun, FRAME_RETRY_MS};
use crate::lifecycle::{self, Lifecycle, Phase};
use crate::passes::{Decision, Passes};
use crate::tiles::{Action, Event, Scheduler};
use crate::Millis;

/// Something the executor tells the core.
#[derive(Clone, Debug, PartialEq)]
pub enum Input {
    /// About tiles and workers: a worker joined, a result came, an operator's control.
    Tiles(Event),
    /// About jobs: a row written, an image stored, a client's cancel or delete.
    Job(lifecycle::Event),
    /// Storage can write (`Ok`) or cannot (`Err`, why): both machines hear it.
    Storage(Result<(), String>),
    /// About a job rendered in passes: a pass's totals, results taken back.
    Pass(PassInput),
    /// About a sequence: its row written, an operator's control.
    Sequence(SequenceInput),
    /// A machine was caught returning wrong pixels for a tile of `caught_in` (`reason`
    /// says how, for people): it gets no tile again, and what it rendered of the
    /// active jobs (not those in passes, whose states the executor takes back with
    /// [`PassInput::TakeBack`]) is rendered again.
    Quarantine {
        machine: String,
        caught_in: JobId,
        reason: String,
    },
    /// A straggler's second copy of an accepted tile, compared with the accepted one
    /// by the executor (which holds the pixels) and, if they differ, arbitrated by
    /// rendering the pixels where they do: the core quarantines whichever copy's
    /// machine is shown wrong.
    Duplicate(Duplicate),
    /// The time has come ([`Farm::next_deadline`]).
    Timeout,
}

/// Something the executor carries out: every action of either machine, in the order
/// they were made, the follow-ups the core fed back included (for the executor to log
/// and count; it must not feed them again).
#[derive(Clone, Debug, PartialEq)]
pub enum Effect {
    Tiles(Action),
    Job(lifecycle::Action),
    Pass(PassAction),
    Sequence(SequenceAction),
    /// A machine is quarantined ([`Input::Quarantine`], or a copy shown wrong): the
    /// executor shuts it out of what it keeps (results held, jobs in passes) and says
    /// so in the events of `caught_in` and of the jobs in `taken` (tiles of which it
    /// rendered, taken back: each follows as [`Effect::TakenBack`]).
    Quarantined {
        machine: String,
        caught_in: JobId,
        reason: String,
        taken: Vec<(JobId, Vec<u32>)>,
    },
    /// A duplicate copy settled nothing: equal to the accepted one, or different with
    /// neither shown wrong (no renderer to arbitrate); the executor logs it.
    DuplicateSettled {
        job: JobId,
        tile: u32,
        machine: String,
        same: bool,
    },
    /// Tiles of `job` accepted from a quarantined machine, taken back: the executor
    /// forgets their pixels (and what it stored of them); they go out again.
    TakenBack {
        job: JobId,
        tiles: Vec<u32>,
    },
    /// A stored job waits for the jobs it was submitted after: `on`, those not yet
    /// done. Its tiles go out once they are ([`Effect::Released`]).
    Waiting {
        job: JobId,
        on: Vec<JobId>,
    },
    /// Every job a waiting job was submitted after is done: its tiles go out.
    Released {
        job: JobId,
    },
}

/// How a job's tiles go out once it is stored: what [`Event::JobSubmitted`] needs, and
/// how its last tile is taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TilePlan {
    pub priority: i32,
    pub scene: SceneHash,
    pub tiles: u32,
    /// A studio view's pass: its tiles go ahead of batch jobs.
    pub interactive: bool,
}

/// The tile scheduler and the lifecycle, joined by the rules above.
pub struct Farm {
    tiles: Scheduler,
    lifecycle: Lifecycle,
    /// The plan of every job the core has been told of, until it is deleted.
    plans: BTreeMap<JobId, TilePlan>,
    /// The jobs rendered in passes ([`Farm::start_passes`]), until they are deleted.
    passes: BTreeMap<JobId, PassRun>,
    /// Which machine rendered each accepted tile of the active jobs.
    renderers: Renderers,
    /// The worker whose result the input under way is, if it is one.
    reporter: Option<WorkerId>,
    /// The sequences, until they are deleted.
    sequences: BTreeMap<JobId, SequenceRun>,
    /// Each frame job admitted and not deleted: its sequence and frame.
    frame_jobs: BTreeMap<JobId, (JobId, u32)>,
    /// The sequences that may start frames once the input under way is handled: a
    /// frame's tile went out, a frame ended, an operator's control.
    to_fill: BTreeSet<JobId>,
    /// Which jobs were submitted after which, and which wait.
    dependencies: Dependencies,
}

impl Farm {
    pub fn new(tiles: Scheduler, lifecycle: Lifecycle) -> Farm {
        Farm {
            tiles,
            lifecycle,
            plans: BTreeMap::new(),
            passes: BTreeMap::new(),
            renderers: Renderers::default(),
            reporter: None,
            sequences: BTreeMap::new(),
            frame_jobs: BTreeMap::new(),
            to_fill: BTreeSet::new(),
            dependencies: Dependencies::default(),
        }
    }

    /// Which jobs were submitted after which, and which wait.
    pub fn dependencies(&self) -> &Dependencies {
        &self.dependencies
    }

    /// The tile scheduler, to read.
    pub fn tiles(&self) -> &Scheduler {
        &self.tiles
    }

    /// The lifecycle, to read.
    pub fn lifecycle(&self) -> &Lifecycle {
        &self.lifecycle
    }

    /// A job rendered in passes: where its pass under way stands.
    pub fn pass_run(&self, job: JobId) -> Option<&PassRun> {
        self.passes.get(&job)
    }

    /// A sequence, while it is not deleted.
    pub fn sequence(&self, sequence: JobId) -> Option<&SequenceRun> {
        self.sequences.get(&sequence)
    }

    /// Every sequence, by id.
    pub fn sequences(&self) -> impl Iterator<Item = (JobId, &SequenceRun)> + '_ {
        self.sequences.iter().map(|(&id, run)| (id, run))
    }

    /// The earliest time at which either machine has something to decide, or a
    /// sequence tries again to start a frame.
    pub fn next_deadline(&self) -> Option<Millis> {
        [
            self.tiles.next_deadline(),
            self.lifecycle.next_deadline(),
            self.frame_retry_at(),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Whether the last input stopped handing out tiles at the bound of one call
    /// ([`Policy::handout_per_call`](crate::Policy::handout_per_call)): the executor
    /// feeds `Input::Tiles(Event::Continue)` at once, after anything that arrived
    /// meanwhile.
    pub fn has_more(&self) -> bool {
        self.tiles.has_more()
    }

    /// Feeds one input, and the follow-ups it causes, at `now`.
    pub fn handle(&mut self, now: Millis, input: Input) -> Vec<Effect> {
        let mut effects = Vec::new();
        match input {
            Input::Tiles(event) => {
                // The worker whose result this is (who rendered what it accepts), and
                // one leaving (forgotten once its tiles went back).
                let mut left = None;
                match &event {
                    // A job not yet stored goes out at its new priority.
                    Event::SetPriority { job, priority } => {
                        if let Some(plan) = self.plans.get_mut(job) {
                            plan.priority = *priority;
                        }
                    }
                    // A pause outlives the pass it came in.
                    Event::PauseJob { job } | Event::ResumeJob { job } => {
                        if let Some(run) = self.passes.get_mut(job) {
                            run.set_paused(matches!(event, Event::PauseJob { .. }));
                        }
                    }
                    Event::WorkerJoined {
                        worker, machine, ..
                    } => self.renderers.joined(*worker, machine.as_deref()),
                    Event::RequeueTiles { job, tiles } => self.renderers.requeued(*job, tiles),
                    Event::TileDone { worker, .. } | Event::TileToConfirm { worker, .. } => {
                        self.reporter = Some(*worker);
                    }
                    Event::WorkerLeft { worker } => left = Some(*worker),
                    _ => {}
                }
                let joined = matches!(event, Event::WorkerJoined { .. });
                self.tiles_event(now, event, &mut effects);
                self.reporter = None;
                if let Some(worker) = left {
                    self.renderers.left(worker);
                }
                if joined {
                    // More credit: a sequence may start another frame to keep it busy.
                    self.to_fill.extend(self.sequences.keys());
                }
            }
            Input::Quarantine {
                machine,
                caught_in,
                reason,
            } => self.quarantine(now, machine, caught_in, reason, &mut effects),
            Input::Duplicate(duplicate) => self.duplicate(now, duplicate, &mut effects),
            Input::Job(event) => self.job_event(now, event, &mut effects),
            Input::Pass(input) => self.pass_input(now, input, &mut effects),
            Input::Sequence(input) => self.sequence_input(now, input, &mut effects),
            Input::Storage(Err(reason)) => {
                self.tiles_event(now, Event::StorageUnavailable, &mut effects);
                let event = lifecycle::Event::StorageUnavailable { reason };
                self.job_event(now, event, &mut effects);
            }
            Input::Storage(Ok(())) => {
                self.job_event(now, lifecycle::Event::StorageAvailable, &mut effects);
                self.tiles_event(now, Event::StorageAvailable, &mut effects);
                self.to_fill.extend(self.sequences.keys());
            }
            Input::Timeout => {
                self.tiles_event(now, Event::Timeout, &mut effects);
                self.job_event(now, lifecycle::Event::Timeout, &mut effects);
                // Frames refused admission try again once their wait is over; and
                // whatever else changed is looked at once more.
                self.to_fill.extend(self.sequences.keys());
            }
        }
        self.fill(now, &mut effects);
        effects
    }

    /// Checks a submission and enters it ([`Lifecycle::admit`]); its tiles go out as
    /// `plan` says once its row is written.
    pub fn admit(
        &mut self,
        now: Millis,
        request: &lifecycle::Request,
        plan: TilePlan,
    ) -> Result<JobId, Refusal> {
        self.admit_after(now, request, plan, &[])
    }

    /// [`Farm::admit`] for a job submitted after the jobs `after`: each must be a job
    /// of the lifecycle (not a sequence), stored. It waits for them once stored.
    pub fn admit_after(
        &mut self,
        now: Millis,
        request: &lifecycle::Request,
        plan: TilePlan,
        after: &[JobId],
    ) -> Result<JobId, Refusal> {
        self.check_after(after)?;
        let job = self.lifecycle.admit(now, request)?;
        self.plans.insert(job, plan);
        self.dependencies.declare(job, after);
        Ok(job)
    }

    /// Whether a job may be submitted after the jobs `after`.
    fn check_after(&self, after: &[JobId]) -> Result<(), Refusal> {
        if after.len() > protocol::MAX_AFTER {
            return Err(Refusal::invalid(format!(
                "after: {} jobs, more than the {} a job may wait for",
                after.len(),
                protocol::MAX_AFTER
            )));
        }
        for &dependency in after {
            if self.sequences.contains_key(&dependency) {
                return Err(Refusal::invalid(format!(
                    "after: job {dependency} is a sequence: a job waits for jobs of one \
                     frame (a sequence's frames are jobs of their own)"
                )));
            }
            match self.lifecycle.job(dependency).map(|j| &j.phase) {
                None | Some(Phase::Storing) => {
                    return Err(Refusal::not_found(format!(
                        "after: there is no job {dependency} to wait for"
                    )))
                }
                Some(_) => {}
            }
        }
        Ok(())
    }

    /// Records that a job taken back (after a restart) was submitted after `after`:
    /// told before [`Farm::resume_job`], which then keeps its tiles back while it
    /// waits.
    pub fn declare_after(&mut self, job: JobId, after: &[JobId]) {
        self.dependencies.declare(job, after);
    }

    /// Whether the job may go back to the queue ([`Lifecycle::check_retry`]), and its
    /// dependencies let it: none failed or cancelled (retry those first), none deleted.
    pub fn check_retry(&self, job: JobId, pixels: u64) -> Result<(), Refusal> {
        self.lifecycle.check_retry(job, pixels)?;
        self.check_retry_dependencies(job)
    }

    fn check_retry_dependencies(&self, job: JobId) -> Result<(), Refusal> {
        for &dependency in self.dependencies.after(job) {
            match self.lifecycle.job(dependency).map(|j| &j.phase) {
                None => {
                    return Err(Refusal::state(format!(
                        "job {job} cannot be retried: job {dependency}, which it waits \
                         for, was deleted (submit the scene again)"
                    )))
                }
                Some(Phase::Ended {
                    state: state @ (JobState::Failed | JobState::Cancelled),
                    ..
                }) => {
                    return Err(Refusal::state(format!(
                        "job {job} cannot be retried before job {dependency}, which it \
                         waits for and which is {}: retry job {dependency} first",
                        state.as_str()
                    )))
                }
                Some(_) => {}
            }
        }
        Ok(())
    }

    /// What the job's dependencies say now: go, wait for some, or fail because one
    /// failed or was cancelled. A dependency no longer kept counts as done: it can
    /// only have been deleted once it ended, and had it not ended done, the jobs
    /// depending on it would have failed first.
    fn gate(&self, job: JobId) -> Gate {
        let mut on = BTreeSet::new();
        for &dependency in self.dependencies.after(job) {
            match self.lifecycle.job(dependency).map(|j| &j.phase) {
                None
                | Some(Phase::Ended {
                    state: JobState::Done,
                    recorded: true,
                    ..
                }) => {}
                Some(Phase::Ended {
                    state,
                    error,
                    recorded: true,
                }) => return Gate::Fail(dependency_failed(dependency, *state, error.as_deref())),
                Some(_) => {
                    on.insert(dependency);
                }
            }
        }
        if on.is_empty() {
            Gate::Go
        } else {
            Gate::Wait(on)
        }
    }

    /// A stored job's tiles go out, unless its dependencies keep them back (it then
    /// waits) or one of them failed (it then fails).
    fn start_or_wait(&mut self, now: Millis, job: JobId, done: &[u32], effects: &mut Vec<Effect>) {
        match self.gate(job) {
            Gate::Go => self.resume(now, job, done, effects),
            Gate::Wait(on) => {
                effects.push(Effect::Waiting {
                    job,
                    on: on.iter().copied().collect(),
                });
                self.dependencies.wait(job, on);
            }
            Gate::Fail(message) => {
                self.job_event(now, lifecycle::Event::TilesFailed { job, message }, effects);
            }
        }
    }

    /// `job`'s end is written: the jobs waiting for it go on (done) or fail.
    fn dependency_ended(&mut self, now: Millis, job: JobId, effects: &mut Vec<Effect>) {
        let Some(Phase::Ended { state, error, .. }) =
            self.lifecycle.job(job).map(|j| j.phase.clone())
        else {
            return;
        };
        if state == JobState::Done {
            for released in self.dependencies.done(job) {
                effects.push(Effect::Released { job: released });
                self.resume(now, released, &[], effects);
            }
        } else {
            let message = dependency_failed(job, state, error.as_deref());
            for dependent in self.dependencies.waiting_on(job) {
                self.dependencies.stop_waiting(dependent);
                let event = lifecycle::Event::TilesFailed {
                    job: dependent,
                    message: message.clone(),
                };
                self.job_event(now, event, effects);
            }
        }
    }

    /// Renders `job` in passes, from the first of `passes`: its last tile ends a pass
    /// rather than the job. Told before its tiles first go out (after
    /// [`Farm::admit`], or before [`Farm::resume_job`] for a job taken back).
    pub fn start_passes(&mut self, job: JobId, passes: Passes) {
        self.passes.insert(job, PassRun::new(passes));
    }

    /// The worker tags the job requires (none: any worker), told before its tiles go
    /// out ([`Farm::admit`], [`Farm::resume_job`]) as [`Event::RequireTags`]. The job
    /// is not active then, so nothing is handed out and nothing follows.
    pub fn require(&mut self, now: Millis, job: JobId, tags: &[String]) {
        debug_assert!(
            !self.tiles.is_active(job),
            "requirements are told before a job's tiles go out"
        );
        let event = Event::RequireTags {
            job,
            tags: tags.to_vec(),
        };
        let actions = self.tiles.handle(now, event);
        debug_assert!(actions.is_empty(), "{actions:?}");
    }

    /// Hands out a job's tiles but `done` at once, without a submission: a job taken
    /// back after a restart or a retry.
    pub fn resume_job(
        &mut self,
        now: Millis,
        job: JobId,
        plan: TilePlan,
        done: &[u32],
    ) -> Vec<Effect> {
        self.plans.insert(job, plan);
        let mut effects = Vec::new();
        self.start_or_wait(now, job, done, &mut effects);
        effects
    }

    /// Hands out the job's tiles but `done`, as its plan says.
    fn resume(&mut self, now: Millis, job: JobId, done: &[u32], effects: &mut Vec<Effect>) {
        let Some(plan) = self.plans.get(&job).copied() else {
            return;
        };
        let actions = self
            .tiles
            .resume_job(now, job, plan.priority, plan.scene, plan.tiles, done);
        self.follow(now, actions, effects);
        if plan.interactive {
            self.tiles_event(now, Event::Interactive { job }, effects);
        }
    }

    /// Whether the lifecycle has the job queued or running: passes still count.
    fn passing(&self, job: JobId) -> bool {
        self.lifecycle
            .job(job)
            .is_some_and(|j| matches!(j.phase, Phase::Queued | Phase::Running))
    }

    fn pass_input(&mut self, now: Millis, input: PassInput, effects: &mut Vec<Effect>) {
        match input {
            PassInput::Evaluated {
                job,
                pass,
                checks,
                tiles,
                elapsed_ms,
                samples,
            } => {
                let passing = self.passing(job);
                let Some(run) = self.passes.get_mut(&job).filter(|r| r.awaits(pass)) else {
                    // A pass restarted or a job ended meanwhile: it counts for nothing.
                    return;
                };
                if !passing {
                    run.failed();
                    return;
                }
                let (rung, out_of_time) = match run.evaluated(&checks, &tiles, elapsed_ms, samples)
                {
                    Decision::Finish { rung } => (rung, false),
                    Decision::OutOfTime { rung } => (rung, true),
                    Decision::Next { rung } => {
                        let pass = run.pass();
                        effects.push(Effect::Pass(PassAction::Continued { job, pass, rung }));
                        self.start_pass(now, job, &tiles, effects);
                        return;
                    }
                };
                effects.push(Effect::Pass(PassAction::Finished {
                    job,
                    pass,
                    rung,
                    out_of_time,
                }));
                self.job_event(now, lifecycle::Event::TilesComplete { job }, effects);
            }
            PassInput::Failed { job, pass, message } => {
                let passing = self.passing(job);
                let Some(run) = self.passes.get_mut(&job).filter(|r| r.awaits(pass)) else {
                    return;
                };
                run.failed();
                if passing {
                    let message = format!("cannot add up the pass's tiles: {message}");
                    self.job_event(now, lifecycle::Event::TilesFailed { job, message }, effects);
                }
            }
            PassInput::TakeBack {
                job,
                taken,
                mut tiles,
            } => {
                if taken.is_empty() || !self.passes.contains_key(&job) {
                    return;
                }
                if !self.passing(job) {
                    effects.push(Effect::Pass(PassAction::TooLate { job, taken }));
                    return;
                }
                let Some(run) = self.passes.get_mut(&job) else {
                    return;
                };
                let pass = run.restart();
                for &t in &taken {
                    if let Some(tile) = tiles.get_mut(t as usize) {
                        *tile = PassTile {
                            rung: None,
                            next_work: Some(0),
                        };
                    }
                }
                effects.push(Effect::Pass(PassAction::TakenBack { job, pass, taken }));
                self.tiles_event(now, Event::CancelJob { job }, effects);
                self.start_pass(now, job, &tiles, effects);
            }
        }
    }

    /// The job's pass under way goes out: the tiles with work at its rung, paused if
    /// an operator paused the job.
    fn start_pass(
        &mut self,
        now: Millis,
        job: JobId,
        tiles: &[PassTile],
        effects: &mut Vec<Effect>,
    ) {
        let Some(run) = self.passes.get(&job) else {
            return;
        };
        let (start, done) = run.start(job, tiles);
        let paused = run.paused();
        effects.push(Effect::Pass(start));
        if paused {
            self.tiles_event(now, Event::PauseJob { job }, effects);
        }
        self.resume(now, job, &done, effects);
    }

    /// Tiles of `job` stored before a restart, with the machine that rendered each:
    /// what a quarantine of one of them takes back. Told after [`Farm::resume_job`].
    pub fn restored_tiles(&mut self, job: JobId, done: &[(u32, &str)]) {
        match self.plans.get(&job) {
            Some(plan) if self.tiles.is_active(job) && !self.passes.contains_key(&job) => {
                self.renderers.restored(job, plan.tiles, done);
            }
            _ => {}
        }
    }

    /// A job id for a job the lifecycle does not run itself (a sequence, whose frames
    /// are jobs of their own).
    pub fn issue_id(&mut self) -> JobId {
        self.lifecycle.issue_id()
    }

    /// Keeps a job past its retention ([`Lifecycle::keep`]).
    pub fn keep(&mut self, job: JobId) {
        self.lifecycle.keep(job);
    }

    fn tiles_event(&mut self, now: Millis, event: Event, effects: &mut Vec<Effect>) {
        let actions = self.tiles.handle(now, event);
        self.follow(now, actions, effects);
    }

    /// The scheduler's actions, each followed by what it causes in the lifecycle.
    fn follow(&mut self, now: Millis, actions: Vec<Action>, effects: &mut Vec<Effect>) {
        for action in actions {
            self.note_renderer(&action);
            let next = match &action {
                Action::Assign { job, .. } => {
                    // Fewer tiles wait: the sequence may start its next frame.
                    if let Some(&(sequence, _)) = self.frame_jobs.get(job) {
                        self.to_fill.insert(sequence);
                    }
                    Some(lifecycle::Event::TileAssigned { job: *job })
                }
                Action::JobDone { job } => match self.passes.get_mut(job) {
                    Some(run) => {
                        let add_up = run.complete(*job);
                        effects.push(Effect::Tiles(action));
                        effects.push(Effect::Pass(add_up));
                        continue;
                    }
                    None => Some(lifecycle::Event::TilesComplete { job: *job }),
                },
                Action::JobFailed { job, message } => Some(lifecycle::Event::TilesFailed {
                    job: *job,
                    message: message.clone(),
                }),
                _ => None,
            };
            effects.push(Effect::Tiles(action));
            if let Some(event) = next {
                self.job_event(now, event, effects);
            }
        }
    }

    /// Keeps who rendered the accepted tiles of the active jobs not in passes.
    fn note_renderer(&mut self, action: &Action) {
        let tiles_of = |job: &JobId| self.plans.get(job).map(|p| p.tiles);
        match *action {
            Action::AcceptTile { job, tile } if !self.passes.contains_key(&job) => {
                if let Some(tiles) = tiles_of(&job) {
                    self.renderers.accepted(job, tile, tiles, self.reporter);
                }
            }
            Action::HoldResult { worker, job, tile } => self.renderers.held(job, tile, worker),
            Action::AcceptHeld { job, tile } if !self.passes.contains_key(&job) => {
                if let Some(tiles) = tiles_of(&job) {
                    self.renderers.accepted_held(job, tile, tiles);
                }
            }
            Action::JobDone { job } | Action::JobFailed { job, .. } => {
                self.renderers.forget_job(job);
            }
            _ => {}
        }
    }

    fn job_event(&mut self, now: Millis, event: lifecycle::Event, effects: &mut Vec<Effect>) {
        let mut end_recorded = None;
        match &event {
            lifecycle::Event::Deleted { job } => {
                // Its requirements were held by id, for its runs: none is to come.
                let forget = Event::RequireTags {
                    job: *job,
                    tags: Vec::new(),
                };
                self.tiles.handle(now, forget);
                self.plans.remove(job);
                self.passes.remove(job);
                self.renderers.forget_job(*job);
                self.frame_jobs.remove(job);
                self.dependencies.forget(*job);
            }
            // A job that a job not yet done depends on stays: that one may still need
            // it (waiting, or failed and to be retried after it).
            lifecycle::Event::Delete { job } => {
                if let Some(dependent) = self.dependencies.dependents(*job).find(|d| {
                    self.lifecycle.job(*d).is_some_and(|j| {
                        !matches!(
                            j.phase,
                            Phase::Ended {
                                state: JobState::Done,
                                ..
                            }
                        )
                    })
                }) {
                    let result = Err(Refusal::state(format!(
                        "job {job} cannot be deleted: job {dependent} depends on it and is \
                         not done (delete job {dependent} first, or let it finish)"
                    )));
                    effects.push(Effect::Job(lifecycle::Action::Reply { job: *job, result }));
                    return;
                }
            }
            lifecycle::Event::Retry { job, .. } => {
                if let Err(refusal) = self.check_retry_dependencies(*job) {
                    let result = Err(refusal);
                    effects.push(Effect::Job(lifecycle::Action::Reply { job: *job, result }));
                    return;
                }
            }
            lifecycle::Event::StoreFailed { job, .. } => {
                self.plans.remove(job);
                self.passes.remove(job);
                self.renderers.forget_job(*job);
            }
            lifecycle::Event::EndRecorded { job } => end_recorded = Some(*job),
            _ => {}
        }
        for action in self.lifecycle.handle(now, event) {
            let mut gate = None;
            let next: Vec<Event> = match &action {
                lifecycle::Action::Acknowledge { job }
                    if !self.dependencies.after(*job).is_empty() =>
                {
                    gate = Some(*job);
                    Vec::new()
                }
                lifecycle::Action::RecordEnd { job, .. } => {
                    self.dependencies.stop_waiting(*job);
                    Vec::new()
                }
                lifecycle::Action::Acknowledge { job } => {
                    self.plans.get(job).map_or_else(Vec::new, |p| {
                        let submitted = Event::JobSubmitted {
                            job: *job,
                            priority: p.priority,
                            scene: p.scene,
                            tiles: p.tiles,
                        };
                        let interactive = p.interactive.then_some(Event::Interactive { job: *job });
                        std::iter::once(submitted).chain(interactive).collect()
                    })
                }
                lifecycle::Action::CancelTiles { job } => {
                    self.renderers.forget_job(*job);
                    vec![Event::CancelJob { job: *job }]
                }
                _ => Vec::new(),
            };
            let stored = match &action {
                lifecycle::Action::Acknowledge { job } => Some((*job, true)),
                lifecycle::Action::RefuseStored { job, .. } => Some((*job, false)),
                _ => None,
            };
            effects.push(Effect::Job(action));
            for event in next {
                self.tiles_event(now, event, effects);
            }
            if let Some(job) = gate {
                self.start_or_wait(now, job, &[], effects);
            }
            if let Some((job, stored)) = stored {
                self.frame_stored(now, job, stored, effects);
            }
        }
        if let Some(job) = end_recorded {
            self.frame_ended(job, effects);
            self.dependency_ended(now, job, effects);
        }
    }
}

/// What a job's dependencies say about it now.
enum Gate {
    Go,
    Wait(BTreeSet<JobId>),
    Fail(String),
}

/// Why a job fails when `dependency`, which it waits for, ended `state`.
fn dependency_failed(dependency: JobId, state: JobState, error: Option<&str>) -> String {
    match (state, error) {
        (JobState::Failed, Some(error)) => {
            format!("job {dependency}, which this job waits for, failed: {error}")
        }
        _ => format!(
            "job {dependency}, which this job waits for, is {}",
            state.as_str()
        ),
    }
}

mod dependencies;
#[cfg(test)]
mod dependency_tests;
#[cfg(test)]
mod dispute_tests;
mod disputes;
mod pass_run;
#[cfg(test)]
mod pass_tests;
mod renderers;
mod sequence_run;
#[cfg(test)]
mod sequence_tests;
#[cfg(test)]
mod tests;
