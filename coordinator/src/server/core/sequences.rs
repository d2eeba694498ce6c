//! Sequence jobs on the daemon: the decisions are [`scheduler::sequence`]'s, this is
//! where they are carried out.
//!
//! A sequence is a row of the jobs table (its scene, settings and label, `frame` and
//! `last_frame` its range) and, per frame, a frame job: an ordinary job with its
//! tiles, checks, image and end, whose row names the sequence and keeps the scene only
//! while it is active, and whose image is stored in the sequence's folder as
//! `frame_0007.png`. Frame jobs are not listed; the sequence's status adds them up.
//! After a restart, a sequence's state is rebuilt from its frame jobs' rows.
//!
//! Here: a sequence admitted, stored and restored, its frames started and ended, and
//! its end written; what operators do to a sequence and see of it is in [`controls`].

use std::sync::Arc;

use protocol::{ClientResponse, JobId, JobState, Refusal, SceneHash, Settings, Verification};
use scheduler::farm::Input;
use scheduler::lifecycle::{self, Phase};
use scheduler::sequence::{FrameState, Sequence};
use tokio::sync::oneshot;
use tracing::{info, warn};

use super::records::{EventLog, Prepared};
use super::{Core, Shared, Write};
use crate::db::{Label, StoredJob, Times, Totals};
use crate::tiling;

mod controls;

/// What the daemon keeps of a sequence job.
pub struct SequenceRecord {
    pub frames: Sequence,
    pub scene: Arc<str>,
    pub hash: SceneHash,
    /// The scene's frame count (frames are named by it: `frame_0007.png`).
    pub frame_count: u32,
    pub settings: Settings,
    pub tile_size: u32,
    pub tiles_per_frame: u32,
    pub priority: i32,
    pub verification: Verification,
    /// What each frame job is admitted as.
    pub request: lifecycle::Request,
    pub label: Label,
    pub times: Times,
    pub log: EventLog,
    /// Its row is written: frames start only then.
    pub stored: bool,
    /// The final state written to its row, if it has ended.
    pub recorded: Option<JobState>,
    /// Being deleted: nothing starts, nothing more is written.
    pub deleting: bool,
    /// Why the last frame could not be admitted, to log it once.
    last_refusal: Option<Refusal>,
    /// What the frame jobs that have ended cost, added up as they end: a status adds
    /// only the active frames' to it, never walking every frame.
    ended_totals: Totals,
}

impl Core {
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
        };
        self.sequences.insert(
            id,
            SequenceRecord {
                frames: Sequence::new(range.first, range.last),
                scene: Arc::from(prepared.scene),
                hash: prepared.hash,
                frame_count: prepared.frame_count,
                settings: prepared.settings,
                tile_size: prepared.tile_size,
                tiles_per_frame: prepared.tiles.len() as u32,
                priority: prepared.priority,
                verification: prepared.verification,
                request: prepared.request,
                label: prepared.label,
                times,
                log: EventLog::new(),
                stored: false,
                recorded: None,
                deleting: false,
                last_refusal: None,
                ended_totals: Totals::default(),
            },
        );
        self.submits.insert(id, reply);
        Ok(stored)
    }

    /// The sequence's row is written (`Ok`) or could not be: the client hears, and its
    /// first frames start.
    pub fn sequence_stored(&mut self, sh: &Arc<Shared>, id: JobId, result: Result<(), String>) {
        let reply = self.submits.remove(&id);
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        match result {
            Ok(()) => {
                record.stored = true;
                let (first, last) = (record.frames.first(), record.frames.last());
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
                self.fill(sh, id);
                sh.changed();
            }
            Err(message) => {
                self.sequences.remove(&id);
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
        let mut frames = Sequence::new(stored.frame, last);
        frames.set_paused(stored.paused);
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
                frames,
                scene: Arc::from(stored.scene),
                hash: stored.hash,
                frame_count,
                settings: stored.settings,
                tile_size: stored.tile_size,
                tiles_per_frame,
                priority: stored.priority,
                verification: stored.verification,
                request,
                label: stored.label,
                times: stored.times,
                log: EventLog::restored(last_event.0, last_event.1),
                stored: true,
                recorded: stored.state.is_final().then_some(stored.state),
                deleting: false,
                last_refusal: None,
                ended_totals: Totals::default(),
            },
        );
    }

    /// Every sequence and frame job is back: a sequence cancelled before the restart
    /// starts none of its pending frames; the others go on.
    pub fn sequences_restored(&mut self, sh: &Arc<Shared>) {
        let ids: Vec<JobId> = self.sequences.keys().copied().collect();
        for id in ids {
            let mut ended = Totals::default();
            if let Some(record) = self.sequences.get(&id) {
                for state in [FrameState::Done, FrameState::Failed, FrameState::Cancelled] {
                    for (_, job) in record.frames.frames_in(state) {
                        if let Some(r) = self.jobs.get(&job) {
                            add_totals(&mut ended, &r.totals);
                        }
                    }
                }
            }
            let Some(record) = self.sequences.get_mut(&id) else {
                continue;
            };
            record.ended_totals = ended;
            if record.recorded == Some(JobState::Cancelled) {
                record.frames.cancel();
            }
            info!(
                job = id,
                done = record.frames.counts().done,
                frames = record.frames.len(),
                "resuming sequence"
            );
            self.settle(sh, id);
            self.fill(sh, id);
        }
    }

    /// Starts the frames the sequence's machine asks for.
    pub fn fill(&mut self, sh: &Arc<Shared>, id: JobId) {
        let Some(record) = self.sequences.get(&id) else {
            return;
        };
        if !record.stored || record.deleting || self.farm.lifecycle().storage_down().is_some() {
            return;
        }
        let tiles = u64::from(record.tiles_per_frame);
        let starting = record.frames.starting() as u64;
        let waiting = record
            .frames
            .active()
            .map(|(_, job)| self.farm.tiles().waiting(job))
            .sum::<u64>()
            + starting * tiles;
        let credit = self.farm.tiles().total_credit();
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        for frame in record.frames.to_start(waiting, credit, tiles) {
            self.start_frame(sh, id, frame);
        }
    }

    /// Gives every sequence the frames it needs (a worker joined: more credit; or
    /// frames wait for admission).
    pub fn fill_all(&mut self, sh: &Arc<Shared>) {
        let ids: Vec<JobId> = self.sequences.keys().copied().collect();
        for id in ids {
            self.fill(sh, id);
        }
    }

    /// Whether a sequence has frames waiting while none of its frames runs (the
    /// admission refused them): the daemon wakes to try again.
    pub fn sequences_waiting(&self) -> bool {
        self.sequences.values().any(|s| {
            s.stored
                && !s.deleting
                && !s.frames.paused()
                && s.frames.counts().pending > 0
                && s.frames.counts().active == 0
        })
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
        };
        // The answer goes to the sequence (see `frame_acknowledged`), not to a client.
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
                record.frames.start_failed(frame);
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

    /// A frame job is stored and its tiles are out to the scheduler.
    pub(super) fn frame_acknowledged(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        frame: u32,
        job: JobId,
    ) {
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        if record.times.started.is_none() {
            // Its first frame is out: the sequence's time in the queue ends.
            let at = self.now.unix_ms;
            record.times.started = Some(at);
            sh.persistence.write(Write::Started {
                job: id,
                at_unix_ms: at,
            });
        }
        if record.frames.started(frame, job) {
            // The sequence was cancelled while this frame was being stored: cancelled
            // once its tiles, already handed out, have reached their workers.
            self.deferred
                .push_back(Input::Job(lifecycle::Event::Cancel { job }));
        }
    }

    /// A frame job could not be stored: its frame waits again.
    pub(super) fn frame_refused(&mut self, id: JobId, frame: u32) {
        if let Some(record) = self.sequences.get_mut(&id) {
            record.frames.start_failed(frame);
        }
    }

    /// A frame job's end is written: its frame is done, failed or cancelled.
    pub(super) fn frame_ended(&mut self, sh: &Arc<Shared>, id: JobId, frame: u32, job: JobId) {
        let state = match self.farm.lifecycle().job(job).map(|j| &j.phase) {
            Some(Phase::Ended { state, .. }) => *state,
            _ => return,
        };
        let error = self.frame_error(job);
        let cost = self.jobs.get(&job).map(|r| r.totals).unwrap_or_default();
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        if !record.frames.ended(frame, job, state) {
            return;
        }
        add_totals(&mut record.ended_totals, &cost);
        if state == JobState::Failed {
            let detail = format!(
                "frame {frame} (job {job}): {}",
                error.as_deref().unwrap_or("failed")
            );
            warn!(job = id, frame, "a frame failed");
            self.log(sh, id, "frame_failed", detail);
        }
        self.settle(sh, id);
        self.fill(sh, id);
        sh.changed();
    }

    fn frame_error(&self, job: JobId) -> Option<String> {
        match self.farm.lifecycle().job(job).map(|j| &j.phase) {
            Some(Phase::Ended { error, .. }) => error.clone(),
            _ => None,
        }
    }

    /// Writes the sequence's end once every frame has ended (and its return to
    /// running if a requeued frame made it run again).
    fn settle(&mut self, sh: &Arc<Shared>, id: JobId) {
        let Some(record) = self.sequences.get(&id) else {
            return;
        };
        let state = record.frames.state();
        if record.deleting || record.recorded == Some(state) {
            return;
        }
        if !state.is_final() {
            if record.recorded.is_some() {
                if let Some(record) = self.sequences.get_mut(&id) {
                    record.recorded = None;
                    record.times.ended = None;
                }
                sh.persistence.write(Write::SequenceRunning { job: id });
            }
            return;
        }
        let totals = self.sequence_totals(id);
        let error = (state == JobState::Failed).then(|| self.failure_summary(id));
        let Some(record) = self.sequences.get_mut(&id) else {
            return;
        };
        record.recorded = Some(state);
        let ended = self.now.unix_ms;
        record.times.ended = Some(ended);
        let times = record.times;
        let c = record.frames.counts();
        let detail = match state {
            JobState::Done => format!("{} frames, {} rays", c.done, totals.rays),
            _ => error
                .clone()
                .unwrap_or_else(|| format!("{} of {} frames done", c.done, record.frames.len())),
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
        let Some(record) = self.sequences.get(&id) else {
            return String::new();
        };
        let failed: Vec<(u32, JobId)> = record.frames.failed().collect();
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
            record.frames.len(),
            listed.join(", ")
        )
    }

    /// What the sequence's frame jobs cost so far, added up.
    fn sequence_totals(&self, id: JobId) -> Totals {
        let Some(record) = self.sequences.get(&id) else {
            return Totals::default();
        };
        let mut totals = record.ended_totals;
        for (_, job) in record.frames.active() {
            if let Some(r) = self.jobs.get(&job) {
                add_totals(&mut totals, &r.totals);
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
