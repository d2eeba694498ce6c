//! The core's part in sequence jobs: when a frame starts, what its frame job's
//! storing and end mean for its frame, and when the sequence has ended (or runs again).
//!
//! [`Sequence`] decides which frames start and what the sequence's state is; this
//! holds one per sequence, with what gates a start (its row written, not being
//! deleted, storage that writes), and joins it to the tile scheduler (what waits, the
//! workers' credit) and the lifecycle (a frame job stored, refused or ended). The
//! executor keeps the bytes (the scene, the label, what the frames cost) and admits
//! the frames the core starts.

use protocol::{JobId, JobState, Refusal};

use super::{Effect, Farm, TilePlan};
use crate::lifecycle::{self, Phase};
use crate::sequence::{FrameState, Sequence};
use crate::Millis;

/// How long a frame refused admission (a limit, the queue full) waits before the
/// sequence tries again, in milliseconds: the refusal names no time at which it
/// would pass, and a second is short next to a frame.
pub const FRAME_RETRY_MS: u64 = 1_000;

/// One sequence in the core.
#[derive(Clone, Debug)]
pub struct SequenceRun {
    frames: Sequence,
    tiles_per_frame: u32,
    /// Its row is written: frames start only then.
    stored: bool,
    /// Being deleted: nothing starts, nothing more is written.
    deleting: bool,
    /// The final state written to its row, if it has ended.
    recorded: Option<JobState>,
    /// A frame was refused admission: no frame starts before this time.
    retry_at: Option<Millis>,
}

impl SequenceRun {
    /// A sequence just admitted, frames `first..=last` of `tiles_per_frame` tiles
    /// each: its frames start once its row is written ([`SequenceInput::Stored`]).
    pub fn new(first: u32, last: u32, tiles_per_frame: u32) -> SequenceRun {
        SequenceRun {
            frames: Sequence::new(first, last),
            tiles_per_frame,
            stored: false,
            deleting: false,
            recorded: None,
            retry_at: None,
        }
    }

    /// A sequence found stored at a restart, paused or not, with the final state its
    /// row holds if it had ended; its frames follow ([`super::Farm::restore_frame`]).
    pub fn restored(
        first: u32,
        last: u32,
        tiles_per_frame: u32,
        paused: bool,
        recorded: Option<JobState>,
    ) -> SequenceRun {
        let mut run = SequenceRun::new(first, last, tiles_per_frame);
        run.frames.set_paused(paused);
        run.stored = true;
        run.recorded = recorded;
        run
    }

    /// Its frames.
    pub fn frames(&self) -> &Sequence {
        &self.frames
    }

    pub fn tiles_per_frame(&self) -> u32 {
        self.tiles_per_frame
    }

    /// Its row is written (clients see it).
    pub fn stored(&self) -> bool {
        self.stored
    }

    pub fn deleting(&self) -> bool {
        self.deleting
    }

    /// The final state written to its row, if it has ended.
    pub fn recorded(&self) -> Option<JobState> {
        self.recorded
    }

    /// Whether frames may start at `now`.
    pub(super) fn may_start(&self, now: Millis) -> bool {
        self.stored && !self.deleting && self.retry_at.is_none_or(|at| at <= now)
    }

    /// When a frame refused admission is tried again, if one was.
    pub fn retry_at(&self) -> Option<Millis> {
        self.retry_at
    }

    /// A frame was refused: it waits, and the sequence tries again later.
    fn refused(&mut self, frame: u32, now: Millis) {
        self.frames.start_failed(frame);
        self.retry_at = Some(now + FRAME_RETRY_MS);
    }

    pub(super) fn set_stored(&mut self) {
        self.stored = true;
    }

    pub(super) fn set_deleting(&mut self) {
        self.deleting = true;
    }

    /// What its row should say now, if that differs from what it says: the
    /// sequence's end (`Some`), or its return to running after a frame was requeued
    /// (`None`); noted as written.
    pub(super) fn settle(&mut self) -> Option<Option<JobState>> {
        let state = self.frames.state();
        if self.deleting || self.recorded == Some(state) {
            return None;
        }
        if state.is_final() {
            self.recorded = Some(state);
            return Some(Some(state));
        }
        self.recorded.take().map(|_| None)
    }
}

/// Something the executor tells the core about a sequence. A frame job's row
/// written, refused or ended reaches the core through the lifecycle, as any job's.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SequenceInput {
    /// Its row is written: its first frames start.
    Stored { sequence: JobId },
    /// Its row could not be written: it is forgotten.
    NotStored { sequence: JobId },
    /// Every sequence and frame job stored before a restart is back: a sequence
    /// cancelled then starts none of its pending frames; the others go on.
    Restored,
    /// An operator cancels it: frames not started never will; its frame jobs are
    /// cancelled.
    Cancel { sequence: JobId },
    /// An operator pauses (no frame starts) or resumes it; the executor pauses its
    /// frame jobs ([`SequenceAction::Paused`]).
    Pause { sequence: JobId, paused: bool },
    /// An operator has these done, failed or cancelled frames rendered again; their
    /// old frame jobs are deleted.
    Requeue { sequence: JobId, frames: Vec<u32> },
    /// An operator deletes it (it has ended): its frame jobs are deleted, then the
    /// executor deletes its row and folder.
    Delete { sequence: JobId },
    /// Its row and folder are gone.
    Deleted { sequence: JobId },
}

/// Something the executor carries out for a sequence.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SequenceAction {
    /// Admit these frames as frame jobs ([`super::Farm::admit_frame`]), in order.
    StartFrames { sequence: JobId, frames: Vec<u32> },
    /// A frame job is stored: its tiles go out (the sequence's first one ends its
    /// time in the queue).
    FrameOut {
        sequence: JobId,
        frame: u32,
        job: JobId,
    },
    /// A frame job's end is written: its frame is done, failed or cancelled (add up
    /// what it cost).
    FrameEnded {
        sequence: JobId,
        frame: u32,
        job: JobId,
        state: JobState,
    },
    /// Every frame has ended: write the sequence's end.
    Ended { sequence: JobId, state: JobState },
    /// A frame was requeued after the sequence ended: write that it runs again.
    Running { sequence: JobId },
    /// Frames requeued: their old frame jobs (`old`) are deleted next, after the
    /// executor took what they cost off the sequence's.
    Requeued {
        sequence: JobId,
        frames: Vec<u32>,
        old: Vec<JobId>,
    },
    /// Pause or resume these frame jobs with their sequence.
    Paused {
        sequence: JobId,
        paused: bool,
        jobs: Vec<JobId>,
    },
    /// Its frame jobs are being deleted: delete its row and folder after them, then
    /// tell [`SequenceInput::Deleted`].
    DeleteStored { sequence: JobId },
}

impl Farm {
    /// Enters a sequence: one just admitted ([`SequenceRun::new`]) or found stored at a
    /// restart ([`SequenceRun::restored`]), under an id from [`Farm::issue_id`].
    pub fn enter_sequence(&mut self, sequence: JobId, run: SequenceRun) {
        self.sequences.insert(sequence, run);
    }

    /// Admits a frame the core started ([`SequenceAction::StartFrames`]) as a frame
    /// job ([`Farm::admit`]). Refused, the frame waits again, and the sequence tries
    /// again in [`FRAME_RETRY_MS`].
    pub fn admit_frame(
        &mut self,
        now: Millis,
        sequence: JobId,
        frame: u32,
        request: &lifecycle::Request,
        plan: TilePlan,
    ) -> Result<JobId, Refusal> {
        match self.admit(now, request, plan) {
            Ok(job) => {
                self.frame_jobs.insert(job, (sequence, frame));
                Ok(job)
            }
            Err(refusal) => {
                if let Some(run) = self.sequences.get_mut(&sequence) {
                    run.refused(frame, now);
                }
                Err(refusal)
            }
        }
    }

    /// A frame job found stored at a restart, as it stood: told after its sequence
    /// ([`Farm::enter_sequence`]) and before [`SequenceInput::Restored`].
    pub fn restore_frame(&mut self, sequence: JobId, frame: u32, job: JobId, state: JobState) {
        if let Some(run) = self.sequences.get_mut(&sequence) {
            run.frames.restore(frame, job, state);
            self.frame_jobs.insert(job, (sequence, frame));
        }
    }

    /// When the first sequence whose frame was refused tries again (not while
    /// storage cannot write: storage writing again starts what may start).
    pub(super) fn frame_retry_at(&self) -> Option<Millis> {
        if self.lifecycle.storage_down().is_some() {
            return None;
        }
        self.sequences
            .values()
            .filter(|r| r.stored && !r.deleting)
            .filter_map(SequenceRun::retry_at)
            .min()
    }

    pub(super) fn sequence_input(
        &mut self,
        now: Millis,
        input: SequenceInput,
        effects: &mut Vec<Effect>,
    ) {
        match input {
            SequenceInput::Stored { sequence } => {
                if let Some(run) = self.sequences.get_mut(&sequence) {
                    run.set_stored();
                    self.to_fill.insert(sequence);
                }
            }
            SequenceInput::NotStored { sequence } | SequenceInput::Deleted { sequence } => {
                self.sequences.remove(&sequence);
            }
            SequenceInput::Restored => {
                let ids: Vec<JobId> = self.sequences.keys().copied().collect();
                for sequence in ids {
                    if let Some(run) = self.sequences.get_mut(&sequence) {
                        if run.recorded == Some(JobState::Cancelled) {
                            run.frames.cancel();
                        }
                    }
                    self.settle(sequence, effects);
                    self.to_fill.insert(sequence);
                }
            }
            SequenceInput::Cancel { sequence } => {
                let Some(run) = self.sequences.get_mut(&sequence) else {
                    return;
                };
                for job in run.frames.cancel() {
                    self.frame_job_event(now, lifecycle::Event::Cancel { job }, effects);
                }
                self.settle(sequence, effects);
            }
            SequenceInput::Pause { sequence, paused } => {
                let Some(run) = self.sequences.get_mut(&sequence) else {
                    return;
                };
                run.frames.set_paused(paused);
                let jobs = run.frames.active().map(|(_, job)| job).collect();
                effects.push(Effect::Sequence(SequenceAction::Paused {
                    sequence,
                    paused,
                    jobs,
                }));
                if !paused {
                    self.to_fill.insert(sequence);
                }
            }
            SequenceInput::Requeue { sequence, frames } => {
                let Some(run) = self.sequences.get_mut(&sequence) else {
                    return;
                };
                let mut requeued = Vec::new();
                let mut old = Vec::new();
                for frame in frames {
                    if let Ok(job) = run.frames.requeue(frame) {
                        requeued.push(frame);
                        old.extend(job);
                    }
                }
                if requeued.is_empty() {
                    return;
                }
                effects.push(Effect::Sequence(SequenceAction::Requeued {
                    sequence,
                    frames: requeued,
                    old: old.clone(),
                }));
                // The frames' old jobs go: the new ones write their images in their
                // place.
                for job in old {
                    self.frame_job_event(now, lifecycle::Event::Delete { job }, effects);
                }
                self.settle(sequence, effects);
                self.to_fill.insert(sequence);
            }
            SequenceInput::Delete { sequence } => {
                let Some(run) = self.sequences.get_mut(&sequence) else {
                    return;
                };
                run.set_deleting();
                let jobs: Vec<JobId> =
                    [FrameState::Done, FrameState::Failed, FrameState::Cancelled]
                        .into_iter()
                        .flat_map(|s| run.frames.frames_in(s).map(|(_, job)| job))
                        .filter(|&job| job != 0)
                        .collect();
                for job in jobs {
                    self.frame_job_event(now, lifecycle::Event::Delete { job }, effects);
                }
                // After its frames' deletions: the folder goes last.
                effects.push(Effect::Sequence(SequenceAction::DeleteStored { sequence }));
            }
        }
    }

    /// The row of a frame job is written (`stored`) or could not be: its frame is
    /// active (cancelled at once if its sequence was cancelled meanwhile, its tiles
    /// already out), or waits again.
    pub(super) fn frame_stored(
        &mut self,
        now: Millis,
        job: JobId,
        stored: bool,
        effects: &mut Vec<Effect>,
    ) {
        let Some(&(sequence, frame)) = self.frame_jobs.get(&job) else {
            return;
        };
        let Some(run) = self.sequences.get_mut(&sequence) else {
            return;
        };
        if !stored {
            self.frame_jobs.remove(&job);
            run.refused(frame, now);
            // Cancelled meanwhile, the frame is cancelled now: the sequence may have
            // ended.
            self.settle(sequence, effects);
            return;
        }
        let cancel = run.frames.started(frame, job);
        effects.push(Effect::Sequence(SequenceAction::FrameOut {
            sequence,
            frame,
            job,
        }));
        if cancel {
            self.frame_job_event(now, lifecycle::Event::Cancel { job }, effects);
        }
    }

    /// A frame job's end is written: its frame ends with it, and the sequence may end
    /// or start its next frame.
    pub(super) fn frame_ended(&mut self, job: JobId, effects: &mut Vec<Effect>) {
        let Some(&(sequence, frame)) = self.frame_jobs.get(&job) else {
            return;
        };
        let state = match self.lifecycle.job(job).map(|j| &j.phase) {
            Some(Phase::Ended { state, .. }) => *state,
            _ => return,
        };
        let Some(run) = self.sequences.get_mut(&sequence) else {
            return;
        };
        if !run.frames.ended(frame, job, state) {
            return;
        }
        effects.push(Effect::Sequence(SequenceAction::FrameEnded {
            sequence,
            frame,
            job,
            state,
        }));
        self.settle(sequence, effects);
        self.to_fill.insert(sequence);
    }

    /// Feeds the lifecycle an event about a frame job on its sequence's behalf: the
    /// lifecycle's reply to it goes to no client, and is not passed on.
    fn frame_job_event(&mut self, now: Millis, event: lifecycle::Event, effects: &mut Vec<Effect>) {
        let mut caused = Vec::new();
        self.job_event(now, event, &mut caused);
        effects.extend(
            caused
                .into_iter()
                .filter(|e| !matches!(e, Effect::Job(lifecycle::Action::Reply { .. }))),
        );
    }

    /// Tells the executor what to write of the sequence's state, if it changed.
    fn settle(&mut self, sequence: JobId, effects: &mut Vec<Effect>) {
        let Some(change) = self
            .sequences
            .get_mut(&sequence)
            .and_then(SequenceRun::settle)
        else {
            return;
        };
        effects.push(Effect::Sequence(match change {
            Some(state) => SequenceAction::Ended { sequence, state },
            None => SequenceAction::Running { sequence },
        }));
    }

    /// Starts the frames the sequences marked since the last input ask for: a frame
    /// starts when what waits of the active frames would leave the workers' credit
    /// idle ([`Sequence::to_start`]), not while storage cannot write, nor before a
    /// refused frame's wait is over.
    pub(super) fn fill(&mut self, now: Millis, effects: &mut Vec<Effect>) {
        if self.to_fill.is_empty() {
            return;
        }
        if self.lifecycle.storage_down().is_some() {
            // Storage writing again looks at every sequence.
            self.to_fill.clear();
            return;
        }
        let credit = self.tiles.total_credit();
        for sequence in std::mem::take(&mut self.to_fill) {
            let Some(run) = self
                .sequences
                .get_mut(&sequence)
                .filter(|r| r.may_start(now))
            else {
                continue;
            };
            let tiles = u64::from(run.tiles_per_frame);
            let waiting = run
                .frames
                .active()
                .map(|(_, job)| self.tiles.waiting(job))
                .sum::<u64>()
                + run.frames.starting() as u64 * tiles;
            run.retry_at = None;
            let frames = run.frames.to_start(waiting, credit, tiles);
            if !frames.is_empty() {
                effects.push(Effect::Sequence(SequenceAction::StartFrames {
                    sequence,
                    frames,
                }));
            }
        }
    }
}
