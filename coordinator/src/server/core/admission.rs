//! Jobs entering the core: a submission admitted and its row written, and a stored
//! job taken back (at startup, or put back in the queue by an operator).

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use protocol::{ClientResponse, JobState, JobStatus, Refusal, Settings};
use scheduler::farm::TilePlan;
use scheduler::lifecycle;
use scheduler::Event;
use tokio::sync::oneshot;
use tracing::info;

use super::figures;
use super::records::{
    rect_pixels, restored_label, to_render_rect, Accepted, EventLog, JobRecord, Prepared,
};
use super::{unknown, Core, Shared, Write};
use crate::db::{StoredJob, Times, Totals};
use crate::server::adaptive::AdaptiveJob;
use crate::server::startup::RestoredJob;
use crate::tiling;

impl Core {
    /// Enters an admitted job, waiting for its row to be written; `reply` gets the
    /// answer for the client.
    pub fn admit(
        &mut self,
        prepared: Prepared,
        reply: oneshot::Sender<ClientResponse>,
    ) -> Result<StoredJob, Refusal> {
        let plan = TilePlan {
            priority: prepared.priority,
            scene: prepared.hash,
            tiles: prepared.tiles.len() as u32,
            interactive: prepared.interactive,
        };
        let now = self.now.mono;
        let id = match prepared.sequence {
            // A frame the core started: refused, it waits again.
            Some(sequence) => {
                self.farm
                    .admit_frame(now, sequence, prepared.frame, &prepared.request, plan)?
            }
            None => self
                .farm
                .admit_after(now, &prepared.request, plan, &prepared.after)?,
        };
        // Before its row is written, hence before any of its tiles goes out.
        self.farm.require(now, id, &prepared.require);
        let adaptive = is_adaptive(&prepared.settings).then(|| {
            let (adaptive, passes) = AdaptiveJob::new(
                &prepared.settings,
                prepared.tiles.len(),
                prepared.time_limit_ms,
                prepared.start,
            );
            self.farm.start_passes(id, passes);
            adaptive
        });
        let submitted = self.now.unix_ms;
        let stored = StoredJob {
            id,
            scene: prepared.scene.clone(),
            hash: prepared.hash,
            frame: prepared.frame,
            last_frame: None,
            sequence: prepared.sequence,
            assets: prepared.assets.clone(),
            settings: prepared.settings,
            tile_size: prepared.tile_size,
            priority: prepared.priority,
            state: JobState::Queued,
            error: None,
            totals: None,
            times: Times {
                submitted: Some(submitted),
                ..Times::default()
            },
            image_sha256: None,
            verification: prepared.verification,
            time_limit_ms: prepared.time_limit_ms,
            stopped_on_time_limit: false,
            paused: false,
            after: prepared.after.clone(),
            label: prepared.label.clone(),
            require: prepared.require.clone(),
        };
        self.jobs.insert(
            id,
            JobRecord {
                assets: Arc::from(prepared.assets),
                interactive: prepared.interactive,
                owner: prepared.owner,
                adaptive,
                time_limit_ms: prepared.time_limit_ms,
                stopped_on_time_limit: false,
                paused: false,
                label: prepared.label,
                log: EventLog::new(),
                verification: prepared.verification,
                accepted: HashMap::new(),
                scene: Some(Arc::from(prepared.scene)),
                hash: prepared.hash,
                frame: prepared.frame,
                sequence: prepared.sequence,
                settings: prepared.settings,
                tile_size: prepared.tile_size,
                tiles_total: prepared.tiles.len() as u32,
                tiles: prepared.tiles,
                priority: prepared.priority,
                image: None,
                times: stored.times,
                rendered_before_ms: 0,
                running_since: None,
                pace: figures::Pace::default(),
                tiles_recorded: 0,
                totals: Totals::default(),
                tiles_per_worker: BTreeMap::new(),
                image_sha256: None,
                after: prepared.after,
                require: prepared.require,
                measured: Default::default(),
            },
        );
        self.submits.insert(id, reply);
        Ok(stored)
    }

    /// The write that stores an admitted job's row, and then has the lifecycle hear
    /// whether it was stored.
    pub fn insert_write(&self, sh: &Arc<Shared>, stored: StoredJob) -> Write {
        let id = stored.id;
        let shared = Arc::clone(sh);
        let label = stored.label.clone();
        Write::InsertJob {
            job: Box::new(stored),
            then: Box::new(move |result| {
                let event = match result {
                    Ok(()) => {
                        shared.lock().log(
                            &shared,
                            id,
                            "submitted",
                            format!(
                                "{:?} by {} from {}",
                                label.name, label.submitter, label.submitted_from
                            ),
                        );
                        lifecycle::Event::Stored { job: id }
                    }
                    Err(message) => lifecycle::Event::StoreFailed { job: id, message },
                };
                shared.lock().life_event(&shared, event);
            }),
        }
    }

    /// Takes back a job found on disk at startup.
    pub fn restore(&mut self, sh: &Arc<Shared>, restored: RestoredJob) {
        self.take_back(sh, restored, false);
    }

    /// A failed or cancelled job is back in the queue on disk, read back with its
    /// stored tiles: the lifecycle takes it back (or refuses, if it changed since it
    /// was checked), and only its missing tiles are rendered. Returns its status.
    pub fn retried(
        &mut self,
        sh: &Arc<Shared>,
        mut restored: RestoredJob,
        peer: std::net::IpAddr,
    ) -> Result<JobStatus, Refusal> {
        let id = restored.job.id;
        if restored.job.state.is_final() {
            // Found unusable when read back (its scene or settings): recorded failed.
            return Err(Refusal::state(format!(
                "job {id} cannot be retried: {}",
                restored
                    .job
                    .error
                    .as_deref()
                    .unwrap_or("it cannot be rendered")
            )));
        }
        let kept = restored.tiles.len();
        let started = kept > 0 || restored.job.times.started.is_some();
        let pixels =
            u64::from(restored.job.settings.width) * u64::from(restored.job.settings.height);
        let reply = self.life_event(
            sh,
            lifecycle::Event::Retry {
                job: id,
                started,
                pixels,
            },
        );
        if let Some(Err(message)) = reply {
            return Err(message);
        }
        restored.last_event = self.jobs.get(&id).map_or((0, 0), |r| {
            (r.log.next_seq.saturating_sub(1), r.log.dropped)
        });
        self.take_back(sh, restored, true);
        let total = self.jobs.get(&id).map_or(0, |r| r.tiles_total);
        info!(job = id, kept, total, "job retried by an operator");
        self.log(
            sh,
            id,
            "retried",
            format!("from {peer}: {kept} of {total} tiles kept, the others are rendered"),
        );
        sh.changed();
        self.status(id).ok_or_else(|| unknown(id))
    }

    /// Takes back a stored job: its record, its frame from the stored tiles, and its
    /// remaining tiles to the scheduler; the lifecycle learns of it unless it already
    /// has (`retried`).
    fn take_back(&mut self, sh: &Arc<Shared>, restored: RestoredJob, retried: bool) {
        let stored = restored.job;
        let id = stored.id;
        // An adaptive job of an earlier version may have tiles off the blocks: it starts
        // its passes again anyway, on tiles it can use.
        let mut stored = stored;
        if is_adaptive(&stored.settings)
            && verify::adaptive::check_tile_side(stored.tile_size).is_err()
        {
            stored.tile_size = tiling::default_tile_size(&stored.settings);
        }
        let tiles = tiling::cut(&stored.settings, stored.tile_size);
        let final_state = stored.state.is_final();
        let adaptive = (!final_state && is_adaptive(&stored.settings)).then(|| {
            let (adaptive, passes) =
                AdaptiveJob::new(&stored.settings, tiles.len(), stored.time_limit_ms, None);
            self.farm.start_passes(id, passes);
            adaptive
        });
        let mut record = JobRecord {
            assets: Arc::from(stored.assets.clone()),
            interactive: false,
            owner: None,
            adaptive,
            time_limit_ms: stored.time_limit_ms,
            stopped_on_time_limit: stored.stopped_on_time_limit,
            paused: stored.paused && !final_state,
            label: restored_label(id, &stored.label),
            log: EventLog::restored(restored.last_event.0, restored.last_event.1),
            verification: stored.verification,
            accepted: HashMap::new(),
            scene: (!final_state).then(|| Arc::from(stored.scene.as_str())),
            hash: stored.hash,
            frame: stored.frame,
            sequence: stored.sequence,
            settings: stored.settings,
            tile_size: stored.tile_size,
            tiles_total: tiles.len() as u32,
            tiles: if final_state { Vec::new() } else { tiles },
            priority: stored.priority,
            image: None,
            times: Times {
                submitted: stored.times.submitted.or(Some(self.now.unix_ms)),
                ..stored.times
            },
            rendered_before_ms: 0,
            running_since: None,
            pace: figures::Pace::default(),
            tiles_recorded: 0,
            totals: stored.totals.unwrap_or_default(),
            tiles_per_worker: BTreeMap::new(),
            image_sha256: stored.image_sha256,
            after: stored.after.clone(),
            require: stored.require.clone(),
            measured: Default::default(),
        };
        // Before the job is taken back: what it waits for decides whether its tiles go
        // out, and a job that depends on it keeps it from being deleted.
        if !retried {
            self.farm.declare_after(id, &stored.after);
        }
        // A retry starts a new run: its first tile out is the run's start (stored anew
        // when it goes out). What was rendered before still counts in its rate below.
        if record
            .times
            .started
            .zip(record.times.retried)
            .is_some_and(|(started, retried)| started < retried)
        {
            record.times.started = None;
        }
        if let Some(sequence) = stored.sequence {
            self.farm.keep(id);
            self.farm
                .restore_frame(sequence, stored.frame, id, stored.state);
            if let (Some(s), Some(run)) =
                (self.sequences.get(&sequence), self.farm.sequence(sequence))
            {
                // The sequence's controls are its frames'.
                record.paused = run.frames().paused() && !final_state;
                record.priority = s.priority;
            }
        }
        if final_state {
            // Its progress as it ended: all of it, or (cancelled, failed) the tiles it
            // has stored, which a retry keeps.
            record.tiles_recorded = if stored.state == JobState::Done {
                record.tiles_total
            } else {
                restored.stored_tiles.min(record.tiles_total)
            };
            self.jobs.insert(id, record);
            self.life_event(
                sh,
                lifecycle::Event::Restored {
                    job: id,
                    state: stored.state,
                    error: stored.error,
                    started: true,
                    pixels: 0,
                    ended_ago: stored
                        .times
                        .ended
                        .map_or(0, |ended| self.now.unix_ms.saturating_sub(ended)),
                },
            );
            return;
        }
        let mut image = render::Image::black(stored.settings.width, stored.settings.height);
        let mut done = Vec::new();
        let last_done = restored.tiles.iter().filter_map(|t| t.done_ms).max();
        if let (Some(started), Some(last)) = (stored.times.started, last_done) {
            record.rendered_before_ms = last.saturating_sub(started);
        }
        // An adaptive job starts its passes again: its tiles' states are not stored.
        let tiles = if record.adaptive.is_some() {
            Vec::new()
        } else {
            restored.tiles
        };
        for t in tiles {
            let rect = record.tiles[t.tile as usize];
            image.put_rect(to_render_rect(rect), &t.rgb);
            record.tiles_recorded += 1;
            // A tile recorded by an earlier version was a grid render: aa² per pixel.
            let pixels = rect_pixels(rect);
            let aa = u64::from(stored.settings.aa);
            let samples = t.samples.unwrap_or(pixels * aa * aa);
            record.add_cost(t.rays, samples, t.error_sq_sum, pixels);
            record.accepted.insert(
                t.tile,
                Accepted {
                    machine: Arc::from(t.worker.as_str()),
                    rays: t.rays,
                    samples,
                    error_sq_sum: t.error_sq_sum,
                },
            );
            *record.tiles_per_worker.entry(t.worker).or_default() += 1;
            done.push(t.tile);
        }
        record.image = Some(image);
        let plan = Core::plan_of(&record);
        let total = record.tiles_total;
        if record.paused {
            info!(
                job = id,
                "job paused by an operator: none of its tiles goes out"
            );
            self.tiles_event(sh, Event::PauseJob { job: id });
        }
        info!(job = id, done = done.len(), total, "resuming job");
        self.jobs.insert(id, record);
        if !retried {
            self.life_event(
                sh,
                lifecycle::Event::Restored {
                    job: id,
                    state: stored.state,
                    error: None,
                    started: !done.is_empty() || stored.times.started.is_some(),
                    pixels: u64::from(stored.settings.width) * u64::from(stored.settings.height),
                    ended_ago: 0,
                },
            );
        }
        self.farm
            .require(self.now.mono, id, &self.jobs[&id].require);
        let effects = self.farm.resume_job(self.now.mono, id, plan, &done);
        let renderers: Vec<(u32, &str)> = self.jobs[&id]
            .accepted
            .iter()
            .map(|(&tile, a)| (tile, &*a.machine))
            .collect();
        self.farm.restored_tiles(id, &renderers);
        self.carry_out(sh, effects);
    }
}

/// Whether a job's tiles are advanced in passes.
fn is_adaptive(settings: &Settings) -> bool {
    settings.sampling.target_error().is_some()
}
