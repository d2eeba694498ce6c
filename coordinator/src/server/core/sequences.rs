//! Sequence jobs on the daemon: the decisions are the core's
//! ([`scheduler::farm::SequenceRun`]: which frames start and when, what a frame job's
//! storing and end mean, when the sequence has ended); this is where they are
//! carried out.
//!
//! A sequence is a row of the jobs table (its scene, settings and label, `frame` and
//! `last_frame` its range) and, per frame, a frame job: an ordinary job with its
//! tiles, checks, image and end, whose row names the sequence and keeps the scene only
//! while it is active, and whose image is stored in the sequence's folder as
//! `frame_0007.png`. Frame jobs are not listed; the sequence's status adds them up.
//! After a restart, a sequence's state is rebuilt from its frame jobs' rows.
//!
//! Here: a sequence admitted, stored and restored, the frames the core starts
//! admitted, what its frames cost added up, and its end written; what operators do to
//! a sequence and see of it is in [`controls`].

use std::sync::Arc;

use protocol::{ClientResponse, JobId, JobState, Refusal, SceneHash, Settings, Verification};
use scheduler::farm::{Input, SequenceAction, SequenceInput, SequenceRun};
use scheduler::lifecycle::{self, Phase};
use scheduler::sequence::{FrameState, Sequence};
use tokio::sync::oneshot;
use tracing::{info, warn};

use super::records::{EventLog, Prepared};
use super::{Core, Shared, Write};
use crate::db::{Label, StoredJob, Times, Totals};
use crate::store::ImagePlace;
use crate::tiling;

mod controls;

/// What the daemon keeps of a sequence job: its bytes and what it cost. Where its
/// frames stand is the core's ([`Core::sequence_run`]).
pub struct SequenceRecord {
    pub scene: Arc<str>,
    /// The files the scene names: every frame job's.
    pub assets: Arc<[protocol::AssetRef]>,
    pub hash: SceneHash,
    /// The scene's frame count (frames are named by it: `frame_0007.png`).
    pub frame_count: u32,
    pub settings: Settings,
    pub tile_size: u32,
    pub priority: i32,
    pub verification: Verification,
    /// What each frame job is admitted as.
    pub request: lifecycle::Request,
    pub label: Label,
    pub times: Times,
    pub log: EventLog,
    /// Why the last frame could not be admitted, to log it once.
    last_refusal: Option<Refusal>,
    /// What the frame jobs that have ended cost, added up as they end: a status adds
    /// only the active frames' to it, never walking every frame.
    ended_totals: Totals,
    /// Who hears once an operator's deletion is done.
    deleted: Option<oneshot::Sender<()>>,
    /// The worker tags every frame job requires.
    pub require: Vec<String>,
}

impl Core {
    /// Where a sequence's frames stand, while it is not deleted.
    pub fn sequence_run(&self, id: JobId) -> Option<&SequenceRun> {
        self.farm.sequence(id)
    }

    /// Its frames, once its row is written and while it is not being deleted.
    fn stored_frames(&self, id: JobId) -> Option<&Sequence> {
        self.farm
            .sequence(id)
            .filter(|r| r.stored() && !r.deleting())
            .map(SequenceRun::frames)
    }

    /// Enters an admitted sequence, waiting for its row to be written; `reply` gets
    /// the client's answer. Its frames start once it is stored.
    pub fn admit_sequence(
        &mut self,
        prepared: Prepared,
        reply: oneshot::Sender<ClientResponse>,
    ) -> Result<StoredJob, Refusal> {
        let range = prepared.frames.expect("a sequence has a frame range");
        if let Some(reason) = self.farm.lifecycle().storage_down() {
            return Err(Refusal::unavailable(format!(
                "the coordinator cannot store new jobs now (storage unavailable: {reason}): \
                 submit again later"
            )));
        }
        self.farm.lifecycle().limits().check(&prepared.request)?;
        let id = self.farm.issue_id();
        let times = Times {
            submitted: Some(self.now.unix_ms),
            ..Times::default()
        };
        let stored = StoredJob {
            id,
            scene: prepared.scene.clone(),
            hash: prepared.hash,
            frame: range.first,
            last_frame: Some(range.last),
            sequence: None,
            assets: prepared.assets.clone(),
            settings: prepared.settings,
            tile_size: prepared.tile_size,
            priority: prepared.priority,
            state: JobState::Queued,
            error: None,
            totals: None,
            times,
            image_sha256: None,
            verification: prepared.verification,
            time_limit_ms: None,
            stopped_on_time_limit: false,
            paused: false,
            label: prepared.label.clone(),
            after: Vec::new(),
            require: prepared.require.clone(),
        };
        let run = SequenceRun::new(range.first, range.last, prepared.tiles.len() as u32);
        self.farm.enter_sequence(id, run);
        self.sequences.insert(
            id,
            SequenceRecord {
                assets: Arc::from(prepared.assets),
                scene: Arc::from(prepared.scene),
                hash: prepared.hash,
                frame_count: prepared.frame_count,
                settings: prepared.settings,
                tile_size: prepared.tile_size,
                priority: prepared.priority,
                verification: prepared.verification,
                request: prepared.request,
                label: prepared.label,
                times,
                log: EventLog::new(),
                last_refusal: None,
                ended_totals: Totals::default(),
                deleted: None,
                require: prepared.require,
            },
        );
        self.submits.insert(id, reply);
        Ok(stored)
    }

    /// The sequence's row is written (`Ok`) or could not be: the client hears, and its
    /// first frames start.
    pub fn sequence_stored(&mut self, sh: &Arc<Shared>, id: JobId, result: Result<(), String>) {
        let reply = self.submits.remove(&id);
        let Some(record) = self.sequences.get(&id) else {
            return;
        };
        let Some(run) = self.farm.sequence(id) else {
            return;
        };
        match result {
            Ok(()) => {
                let (first, last) = (run.frames().first(), run.frames().last());
                let label = record.label.clone();
                info!(job = id, first, last, "sequence accepted");
                self.log(
                    sh,
                    id,
                    "submitted",
                    format!(
                        "{:?} by {} from {}: frames {first} to {last}",
                        label.name, label.submitter, label.submitted_from
                    ),
                );
                if let Some(reply) = reply {
                    let _ = reply.send(ClientResponse::Submitted { job: id });
                }
                self.feed(sh, Input::Sequence(SequenceInput::Stored { sequence: id }));
            }
            Err(message) => {
                self.sequences.remove(&id);
                sh.depot.release(id, self.now.unix_ms);
                self.feed(
                    sh,
                    Input::Sequence(SequenceInput::NotStored { sequence: id }),
                );
                if let Some(reply) = reply {
                    let _ = reply.send(ClientResponse::Error(Refusal::internal(format!(
                        "the coordinator cannot store new jobs now: {message}"
                    ))));
                }
            }
        }
    }

    /// Takes back a sequence found on disk at startup; its frame jobs follow it (their
    /// ids are higher) and tell it where each frame stands.
    pub fn restore_sequence(&mut self, stored: StoredJob, last_event: (u64, u64)) {
        let id = stored.id;
        let Some(last) = stored.last_frame else {
            return;
        };
        // The scene was checked when the sequence was accepted; parsing it again gives
        // the frame count and the object count its frames are admitted under, so that
        // a limit lowered across the restart applies to the frames still to start.
        let (frame_count, objects) = render::parse_animated(&stored.scene)
            .map(|a| (a.frame_count(), a.base.objects.len()))
            .unwrap_or((last, 0));
        let tiles_per_frame = tiling::cut(&stored.settings, stored.tile_size).len() as u32;
        let recorded = stored.state.is_final().then_some(stored.state);
        let run =
            SequenceRun::restored(stored.frame, last, tiles_per_frame, stored.paused, recorded);
        self.farm.enter_sequence(id, run);
        let request = lifecycle::Request {
            client: stored.label.submitted_from.parse().ok(),
            scene_bytes: stored.scene.len(),
            objects,
            width: stored.settings.width,
            height: stored.settings.height,
            aa: stored.settings.aa,
        };
        self.sequences.insert(
            id,
            SequenceRecord {
                assets: Arc::from(stored.assets),
                scene: Arc::from(stored.scene),
                hash: stored.hash,
                frame_count,
                settings: stored.settings,
                tile_size: stored.tile_size,
                priority: stored.priority,
                verification: stored.verification,
                request,
                label: stored.label,
                times: stored.times,
                log: EventLog::restored(last_event.0, last_event.1),
                last_refusal: None,
                ended_totals: Totals::default(),
                deleted: None,
                require: stored.require,
            },
        );
    }

    /// Every sequence and frame job is back: what the ended frames cost is added up,
    /// and the core takes the sequences back as they stood.
    pub fn sequences_restored(&mut self, sh: &Arc<Shared>) {
        let ids: Vec<JobId> = self.sequences.keys().copied().collect();
        for id in ids {
            let Some(run) = self.farm.sequence(id) else {
                continue;
            };
            let mut ended = Totals::default();
            for state in [FrameState::Done, FrameState::Failed, FrameState::Cancelled] {
                for (_, job) in run.frames().frames_in(state) {
                    if let Some(r) = self.jobs.get(&job) {
                        add_totals(&mut ended, &r.totals);
                    }
                }
            }
            info!(
                job = id,
                done = run.frames().counts().done,
                frames = run.frames().len(),
                "resuming sequence"
            );
            if let Some(record) = self.sequences.get_mut(&id) {
                record.ended_totals = ended;
            }
        }
        self.feed(sh, Input::Sequence(SequenceInput::Restored));
    }

    /// Carries out one of the core's actions about a sequence.
    pub(super) fn apply_sequence(&mut self, sh: &Arc<Shared>, action: SequenceAction) {
        match action {
            SequenceAction::StartFrames { sequence, frames } => {
                for frame in frames {
                    self.start_frame(sh, sequence, frame);
                }
            }
            SequenceAction::FrameOut { sequence, .. } => self.frame_out(sh, sequence),
            SequenceAction::FrameEnded {
                sequence,
                frame,
                job,
                state,
            } => self.frame_ended(sh, sequence, frame, job, state),
            SequenceAction::Ended { sequence, state } => self.sequence_ended(sh, sequence, state),
            SequenceAction::Running { sequence } => {
                if let Some(record) = self.sequences.get_mut(&sequence) {
                    record.times.ended = None;
                }
                sh.persistence
                    .write(Write::SequenceRunning { job: sequence });
            }
            SequenceAction::Requeued { sequence, old, .. } => {
                // What the old frame jobs cost is no longer the sequence's.
                let mut gone = Totals::default();
                for job in &old {
                    if let Some(r) = self.jobs.get(job) {
                        add_totals(&mut gone, &r.totals);
                    }
                }
                if let Some(record) = self.sequences.get_mut(&sequence) {
                    let t = &mut record.ended_totals;
                    t.rays = t.rays.saturating_sub(gone.rays);
                    t.samples = t.samples.saturating_sub(gone.samples);
                    t.error_sq_sum = (t.error_sq_sum - gone.error_sq_sum).max(0.0);
                    t.error_pixels = t.error_pixels.saturating_sub(gone.error_pixels);
                }
            }
            SequenceAction::Paused { paused, jobs, .. } => {
                for job in jobs {
                    // A frame job that has ended meanwhile cannot be paused: nothing
                    // to do.
                    let _ = self.set_paused(sh, job, paused);
                }
            }
            SequenceAction::DeleteStored { sequence } => {
                let shared = Arc::clone(sh);
                // Queued after its frames' deletions: the folder goes last.
                sh.persistence.write(Write::Delete {
                    job: sequence,
                    place: ImagePlace::Job(sequence),
                    then: Box::new(move |_| {
                        let mut core = shared.lock();
                        core.announce_job(&shared, sequence, "deleted", serde_json::json!({}));
                        let done = core
                            .sequences
                            .remove(&sequence)
                            .and_then(|mut r| r.deleted.take());
                        core.feed(
                            &shared,
                            Input::Sequence(SequenceInput::Deleted { sequence }),
                        );
                        let now = core.now.unix_ms;
                        drop(core);
                        shared.depot.release(sequence, now);
                        info!(job = sequence, "sequence deleted");
                        shared.changed();
                        if let Some(done) = done {
                            let _ = done.send(());
                        }
                    }),
                });
            }
        }
    }

    /// Admits frame `frame` of the sequence as a frame job, and stores it.
    fn start_frame(&mut self, sh: &Arc<Shared>, id: JobId, frame: u32) {
        let Some(record) = self.sequences.get(&id) else {
            return;
        };
        let prepared = Prepared {
            interactive: false,
            owner: None,
            scene: record.scene.to_string(),
            hash: record.hash,
            frame,
            settings: record.settings,
            tile_size: record.tile_size,
            tiles: tiling::cut(&record.settings, record.tile_size),
            priority: record.priority,
            verification: record.verification,
            request: record.request,
            time_limit_ms: None,
            start: None,
            label: Label {
                name: format!("{} frame {frame}", record.label.name),
                ..record.label.clone()
            },
            sequence: Some(id),
            frames: None,
            frame_count: record.frame_count,
            assets: record.assets.to_vec(),
            after: Vec::new(),
            require: record.require.clone(),
        };
        // The answer goes to the sequence (the core tells it), not to a client.
        let (reply, _) = oneshot::channel();
        match self.admit(prepared, reply) {
            Ok(stored) => {
                let job = stored.id;
                self.farm.keep(job);
                let write = self.insert_write(sh, stored);
                self.store(sh, job, write);
                if let Some(record) = self.sequences.get_mut(&id) {
                    record.last_refusal = None;
                }
            }
            Err(message) => {
                let Some(record) = self.sequences.get_mut(&id) else {
                    return;
                };
                if record.last_refusal.as_ref() != Some(&message) {
                    warn!(job = id, frame, error = %message, "a frame waits for admission");
                    record.last_refusal = Some(message.clone());
                    self.log(
                        sh,
                        id,
                        "frame_waiting",
                        format!("frame {frame} waits: {message}"),
                    );
                }
            }
        }
    }

    /// A frame job is stored and its tiles are out: the sequence's first one ends its
    /// time in the queue.
    fn frame_out(&mut self, sh: &Arc<Shared>, id: JobId) {
        let at = self.now.unix_ms;
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        if record.times.started.is_none() {
            record.times.started = Some(at);
            sh.persistence.write(Write::Started {
                job: id,
                at_unix_ms: at,
            });
        }
    }

    /// A frame job's end is written: what it cost counts, and a failure is logged.
    fn frame_ended(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        frame: u32,
        job: JobId,
        state: JobState,
    ) {
        if state == JobState::Done {
            let details = serde_json::json!({ "frame": frame, "frame_job": job });
            self.announce_job(sh, id, "frame_done", details);
        }
        let error = self.frame_error(job);
        let cost = self.jobs.get(&job).map(|r| r.totals).unwrap_or_default();
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        add_totals(&mut record.ended_totals, &cost);
        if state == JobState::Failed {
            let detail = format!(
                "frame {frame} (job {job}): {}",
                error.as_deref().unwrap_or("failed")
            );
            warn!(job = id, frame, "a frame failed");
            self.log(sh, id, "frame_failed", detail);
        }
    }

    fn frame_error(&self, job: JobId) -> Option<String> {
        match self.farm.lifecycle().job(job).map(|j| &j.phase) {
            Some(Phase::Ended { error, .. }) => error.clone(),
            _ => None,
        }
    }

    /// Every frame has ended as `state`: the sequence's end is written.
    fn sequence_ended(&mut self, sh: &Arc<Shared>, id: JobId, state: JobState) {
        let totals = self.sequence_totals(id);
        let error = (state == JobState::Failed).then(|| self.failure_summary(id));
        let counts = self
            .farm
            .sequence(id)
            .map(|r| (r.frames().counts(), r.frames().len()));
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        let ended = self.now.unix_ms;
        record.times.ended = Some(ended);
        let times = record.times;
        let (c, frames) = counts.unwrap_or_default();
        let detail = match state {
            JobState::Done => format!("{} frames, {} rays", c.done, totals.rays),
            _ => error
                .clone()
                .unwrap_or_else(|| format!("{} of {frames} frames done", c.done)),
        };
        info!(job = id, state = state.as_str(), "sequence ended");
        self.log(sh, id, state.as_str(), detail);
        sh.persistence.write(Write::End {
            job: id,
            state,
            error,
            totals,
            times,
            image_sha256: None,
            stopped_on_time_limit: false,
            then: Box::new(|_| {}),
        });
    }

    /// Why a sequence failed, in one line: its failed frames and the first error.
    fn failure_summary(&self, id: JobId) -> String {
        let Some(run) = self.farm.sequence(id) else {
            return String::new();
        };
        let failed: Vec<(u32, JobId)> = run.frames().failed().collect();
        let listed: Vec<String> = failed.iter().take(10).map(|(f, _)| f.to_string()).collect();
        let more = if failed.len() > listed.len() {
            format!(" and {} more", failed.len() - listed.len())
        } else {
            String::new()
        };
        let first = failed
            .first()
            .and_then(|&(_, job)| self.frame_error(job))
            .unwrap_or_default();
        format!(
            "{} of {} frames failed (frames {}{more}; requeue them with `tessera retry {id}`): {first}",
            failed.len(),
            run.frames().len(),
            listed.join(", ")
        )
    }

    /// What the sequence's frame jobs cost so far, added up.
    fn sequence_totals(&self, id: JobId) -> Totals {
        let Some(record) = self.sequences.get(&id) else {
            return Totals::default();
        };
        let mut totals = record.ended_totals;
        if let Some(run) = self.farm.sequence(id) {
            for (_, job) in run.frames().active() {
                if let Some(r) = self.jobs.get(&job) {
                    add_totals(&mut totals, &r.totals);
                }
            }
        }
        totals
    }
}

fn add_totals(sum: &mut Totals, more: &Totals) {
    sum.rays += more.rays;
    sum.samples += more.samples;
    sum.error_sq_sum += more.error_sq_sum;
    sum.error_pixels += more.error_pixels;
}

/// Where a sequence's frame jobs are, for a message that asks for one of them: runs of
/// frames whose jobs follow each other (`frames 1-8: jobs 4-11`), and frames not
/// started yet, at most a few runs (then `…`): enough to name a job to give
/// `tessera refine` or `status`, which `tessera list` does not show.
pub(in crate::server) fn frame_jobs(frames: &Sequence) -> String {
    describe_frame_jobs((frames.first()..=frames.last()).map(|k| (k, frames.job(k))))
}

/// [`frame_jobs`] of `(frame, its job if it has one)`, in frame order.
fn describe_frame_jobs(frames: impl Iterator<Item = (u32, Option<JobId>)>) -> String {
    const RUNS: usize = 4;
    // (first frame, last frame, first job of the run if started)
    let mut runs: Vec<(u32, u32, Option<JobId>)> = Vec::new();
    for (k, job) in frames {
        match runs.last_mut() {
            Some((first, last, start))
                if *last + 1 == k
                    && match (*start, job) {
                        (Some(s), Some(j)) => j == s + u64::from(k - *first),
                        (None, None) => true,
                        _ => false,
                    } =>
            {
                *last = k;
            }
            _ => runs.push((k, k, job)),
        }
    }
    let mut parts: Vec<String> = runs
        .iter()
        .take(RUNS)
        .map(|&(first, last, start)| match (first == last, start) {
            (true, Some(job)) => format!("frame {first}: job {job}"),
            (true, None) => format!("frame {first}: not started"),
            (false, Some(job)) => format!(
                "frames {first}-{last}: jobs {job}-{}",
                job + u64::from(last - first)
            ),
            (false, None) => format!("frames {first}-{last}: not started"),
        })
        .collect();
    if runs.len() > RUNS {
        parts.push("…".to_owned());
    }
    parts.join(", ")
}

#[cfg(test)]
mod frame_job_tests {
    use super::*;

    #[test]
    fn frame_jobs_are_named_in_runs() {
        let jobs = |list: &[(u32, Option<JobId>)]| describe_frame_jobs(list.iter().copied());
        assert_eq!(
            jobs(&[(1, Some(4)), (2, Some(5)), (3, Some(6))]),
            "frames 1-3: jobs 4-6"
        );
        assert_eq!(
            jobs(&[(1, Some(4)), (2, Some(9)), (3, None), (4, None)]),
            "frame 1: job 4, frame 2: job 9, frames 3-4: not started"
        );
        assert_eq!(
            jobs(&[
                (1, Some(2)),
                (2, None),
                (3, Some(7)),
                (4, None),
                (5, Some(9))
            ]),
            "frame 1: job 2, frame 2: not started, frame 3: job 7, frame 4: not started, …"
        );
    }
}
