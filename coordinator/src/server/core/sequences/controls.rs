//! What operators do to a sequence (cancel, delete, requeue frames, pause, priority)
//! and what they see of it (its status, its frames' images, the listing), and its
//! deletion once its retention runs out.

use std::sync::Arc;

use protocol::{
    FrameFailure, FrameProgress, JobId, JobState, JobStatus, Refusal, FAILED_FRAMES_LISTED,
};
use scheduler::farm::{Input, SequenceInput, SequenceRun};
use scheduler::sequence::FrameState;
use tokio::sync::oneshot;
use tracing::info;

use crate::server::core::controls::ended_refusal;
use crate::server::core::records::Controls;
use crate::server::core::{unknown, Core};
use crate::server::Shared;
use crate::store::ImagePlace;

impl Core {
    /// A client's view of a sequence: its frames, and its frame jobs added up.
    pub(in crate::server::core) fn sequence_status(&self, id: JobId) -> Option<JobStatus> {
        let record = self.sequences.get(&id)?;
        let run = self.farm.sequence(id).filter(|r| r.stored())?;
        let frames_of = run.frames();
        let state = frames_of.state();
        let c = frames_of.counts();
        let now = self.now.unix_ms;
        let end = record
            .times
            .ended
            .filter(|_| state.is_final())
            .unwrap_or(now);
        let submitted = record.times.submitted.unwrap_or(end);
        let tiles_per_frame = run.tiles_per_frame();
        let mut tiles_done = c.done * tiles_per_frame;
        let started = record.times.started;
        for (_, job) in frames_of.active() {
            if let Some(r) = self.jobs.get(&job) {
                tiles_done += r.tiles_recorded;
            }
        }
        let totals = self.sequence_totals(id);
        let frames = frames_of.len();
        let eta_ms =
            (state == JobState::Running && c.done > 0 && c.done < frames && !frames_of.paused())
                .then(|| {
                    let per_frame = now.saturating_sub(started?) as f64 / f64::from(c.done);
                    Some((per_frame * f64::from(frames - c.done)) as u64)
                })
                .flatten();
        let failures = frames_of
            .failed()
            .take(FAILED_FRAMES_LISTED)
            .map(|(frame, job)| FrameFailure {
                frame,
                job,
                error: self.frame_error(job).unwrap_or_default(),
            })
            .collect();
        let error = (state == JobState::Failed).then(|| self.failure_summary(id));
        let estimated_error =
            (record.settings.aa >= 2 && totals.error_pixels > 0 && state == JobState::Done)
                .then(|| (totals.error_sq_sum / totals.error_pixels as f64).sqrt());
        Some(JobStatus {
            id,
            state,
            settings: record.settings,
            priority: record.priority,
            tiles_done,
            tiles_total: tiles_per_frame * frames,
            rays: totals.rays,
            elapsed_ms: end.saturating_sub(submitted),
            eta_ms,
            error,
            samples: totals.samples,
            estimated_error,
            time_limit_ms: None,
            stopped_on_time_limit: false,
            paused: frames_of.paused() && !state.is_final(),
            warning: (!state.is_final())
                .then(|| {
                    self.no_worker_warning()
                        .or_else(|| self.pool_warning(&record.require, record.verification))
                })
                .flatten(),
            name: record.label.name.clone(),
            submitter: record.label.submitter.clone(),
            submitted_from: record.label.submitted_from.clone(),
            submitted_unix_ms: submitted,
            queued_ms: started.map(|s| s.saturating_sub(submitted)),
            frame: frames_of.first(),
            frames: Some(FrameProgress {
                first: frames_of.first(),
                last: frames_of.last(),
                scene_frames: record.frame_count,
                done: c.done,
                active: c.active,
                pending: c.pending,
                cancelled: c.cancelled,
                done_prefix: frames_of.done_prefix(),
                failed: c.failed,
                failures,
            }),
            sequence: None,
            assets: protocol::JobAssets::of(&record.assets),
            after: Vec::new(),
            waiting_for: Vec::new(),
            require: record.require.clone(),
        })
    }

    /// An operator cancels a sequence: its frames not started never will, its frame
    /// jobs are cancelled.
    pub fn cancel_sequence(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        peer: std::net::IpAddr,
    ) -> Result<(), Refusal> {
        let state = self
            .farm
            .sequence(id)
            .filter(|r| r.stored())
            .ok_or_else(|| unknown(id))?
            .frames()
            .state();
        if state.is_final() {
            return Err(Refusal::state(format!(
                "job {id} is {}: only a queued or running job can be cancelled",
                state.as_str()
            )));
        }
        self.log(sh, id, "cancel", format!("asked from {peer}"));
        self.feed(sh, Input::Sequence(SequenceInput::Cancel { sequence: id }));
        Ok(())
    }

    /// An operator deletes an ended sequence: its frame jobs, then its row and folder.
    /// `done` hears once it is gone.
    pub fn delete_sequence(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        done: oneshot::Sender<()>,
    ) -> Result<(), Refusal> {
        let run = self
            .farm
            .sequence(id)
            .filter(|r| r.stored() && !r.deleting())
            .ok_or_else(|| unknown(id))?;
        let state = run.frames().state();
        if !state.is_final() || run.recorded() != Some(state) {
            return Err(Refusal::state(format!(
                "job {id} is {}: cancel it first",
                if state.is_final() {
                    "still ending"
                } else {
                    state.as_str()
                }
            )));
        }
        if let Some(record) = self.sequences.get_mut(&id) {
            record.deleted = Some(done);
        }
        self.feed(sh, Input::Sequence(SequenceInput::Delete { sequence: id }));
        Ok(())
    }

    /// An operator has a frame rendered again, alone; or, with `frame` `None`, every
    /// failed and cancelled frame (`tessera retry`).
    pub fn requeue_frames(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        frame: Option<u32>,
        peer: std::net::IpAddr,
    ) -> Result<JobStatus, Refusal> {
        let run = self.stored_frames(id).ok_or_else(|| unknown(id))?;
        let frames: Vec<u32> = match frame {
            Some(f) => {
                run.may_requeue(f)
                    .map_err(|e| Refusal::state(format!("job {id}: {e}")))?;
                vec![f]
            }
            None => {
                let again: Vec<u32> = run
                    .failed()
                    .chain(run.frames_in(FrameState::Cancelled))
                    .map(|(f, _)| f)
                    .collect();
                if again.is_empty() {
                    return Err(Refusal::state(format!(
                        "job {id} has no failed or cancelled frame to render again"
                    )));
                }
                again
            }
        };
        let count = frames.len();
        self.feed(
            sh,
            Input::Sequence(SequenceInput::Requeue {
                sequence: id,
                frames,
            }),
        );
        let detail = match frame {
            Some(f) => format!("frame {f}, from {peer}"),
            None => format!("{count} failed or cancelled frames, from {peer}"),
        };
        info!(job = id, frames = count, "frames requeued by an operator");
        self.log(sh, id, "requeued", detail);
        sh.changed();
        self.sequence_status(id).ok_or_else(|| unknown(id))
    }

    /// An operator pauses or resumes a sequence: no frame starts while it is paused,
    /// and its frame jobs are paused or resumed with it.
    pub(in crate::server::core) fn set_sequence_paused(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        paused: bool,
    ) -> Result<Controls, Refusal> {
        let priority = self.controllable(id, if paused { "paused" } else { "resumed" })?;
        self.feed(
            sh,
            Input::Sequence(SequenceInput::Pause {
                sequence: id,
                paused,
            }),
        );
        Ok(Controls {
            job: id,
            paused,
            priority,
        })
    }

    /// An operator gives a sequence a new priority: its frame jobs and those to come.
    pub(in crate::server::core) fn set_sequence_priority(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        priority: i32,
    ) -> Result<Controls, Refusal> {
        self.controllable(id, "given a new priority")?;
        let Some(record) = self.sequences.get_mut(&id) else {
            return Err(unknown(id));
        };
        record.priority = priority;
        let frames = self.stored_frames(id).ok_or_else(|| unknown(id))?;
        let paused = frames.paused();
        let active: Vec<JobId> = frames.active().map(|(_, j)| j).collect();
        for job in active {
            let _ = self.set_priority(sh, job, priority);
        }
        Ok(Controls {
            job: id,
            paused,
            priority,
        })
    }

    /// Whether the sequence takes an operator's control (it is stored and has not
    /// ended); returns its priority.
    fn controllable(&self, id: JobId, verb: &str) -> Result<i32, Refusal> {
        let frames = self.stored_frames(id).ok_or_else(|| unknown(id))?;
        let state = frames.state();
        if state.is_final() {
            return Err(ended_refusal(id, verb, state));
        }
        self.sequences
            .get(&id)
            .map(|r| r.priority)
            .ok_or_else(|| unknown(id))
    }

    /// Where a done frame's image is, and its checksum.
    pub fn frame_image(
        &self,
        id: JobId,
        frame: u32,
    ) -> Result<(ImagePlace, Option<[u8; 32]>), Refusal> {
        let record = self.sequences.get(&id).ok_or_else(|| unknown(id))?;
        let frames = self
            .farm
            .sequence(id)
            .filter(|r| r.stored())
            .map(SequenceRun::frames)
            .ok_or_else(|| unknown(id))?;
        let state = frames.frame(frame).ok_or_else(|| {
            Refusal::not_found(format!(
                "job {id} has frames {} to {}: there is no frame {frame}",
                frames.first(),
                frames.last()
            ))
        })?;
        if state != FrameState::Done {
            return Err(Refusal::state(format!(
                "frame {frame} of job {id} has no image: it is {}",
                match state {
                    FrameState::Pending | FrameState::Starting => "waiting",
                    FrameState::Active => "rendering",
                    FrameState::Failed => "failed",
                    FrameState::Cancelled => "cancelled",
                    FrameState::Done => "done",
                }
            )));
        }
        let job = frames.job(frame).ok_or_else(|| unknown(id))?;
        let sha = self.jobs.get(&job).and_then(|r| r.image_sha256);
        Ok((
            ImagePlace::Frame {
                sequence: id,
                frame,
                count: record.frame_count,
            },
            sha,
        ))
    }

    /// Where a job's image is kept: its own folder, or its sequence's.
    pub fn image_place(&self, job: JobId) -> ImagePlace {
        match self
            .jobs
            .get(&job)
            .and_then(|r| r.sequence.map(|s| (s, r.frame)))
        {
            Some((sequence, frame)) => ImagePlace::Frame {
                sequence,
                frame,
                count: self
                    .sequences
                    .get(&sequence)
                    .map_or(frame, |s| s.frame_count),
            },
            None => ImagePlace::Job(job),
        }
    }

    /// Every job a listing shows: jobs of one frame and sequences, by id; frame jobs
    /// are seen through their sequence.
    pub fn list(&self) -> Vec<JobStatus> {
        let mut list: Vec<JobStatus> = self
            .farm
            .lifecycle()
            .jobs()
            .filter(|(id, _)| self.jobs.get(id).is_some_and(|r| r.sequence.is_none()))
            .filter_map(|(id, _)| self.status(id))
            .chain(
                self.sequences
                    .keys()
                    .filter_map(|&id| self.sequence_status(id)),
            )
            .collect();
        list.sort_by_key(|s| s.id);
        list
    }

    /// Milliseconds until the next ended sequence's retention runs out, if any will.
    pub fn next_sequence_expiry(&self) -> Option<u64> {
        let keep = self.farm.lifecycle().limits().retention?;
        let now = self.now.unix_ms;
        self.sequences
            .iter()
            .filter(|(&id, _)| self.has_ended(id))
            .filter_map(|(_, r)| r.times.ended)
            .map(|ended| ended.saturating_add(keep).saturating_sub(now))
            .min()
    }

    /// Whether the sequence's end is written and it is not being deleted.
    fn has_ended(&self, id: JobId) -> bool {
        self.farm
            .sequence(id)
            .is_some_and(|r| !r.deleting() && r.recorded().is_some())
    }

    /// Sequences whose retention has run out (ended that long ago): deleted.
    pub(in crate::server::core) fn expire_sequences(&mut self, sh: &Arc<Shared>) {
        let Some(keep) = self.farm.lifecycle().limits().retention else {
            return;
        };
        let now = self.now.unix_ms;
        let expired: Vec<JobId> = self
            .sequences
            .iter()
            .filter(|(&id, r)| {
                self.has_ended(id) && r.times.ended.is_some_and(|e| e.saturating_add(keep) <= now)
            })
            .map(|(&id, _)| id)
            .collect();
        for id in expired {
            let (done, _) = oneshot::channel();
            if self.delete_sequence(sh, id, done).is_ok() {
                info!(job = id, "sequence expired: deleted");
            }
        }
    }
}
