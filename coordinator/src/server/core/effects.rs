//! Carrying out the core's effects: the tile scheduler's (scenes and tiles to
//! workers, results accepted or held) and the lifecycle's (a job acknowledged, its
//! image stored, its end written, its deletion).

use std::collections::HashMap;
use std::sync::Arc;

use protocol::{ClientResponse, JobId, JobState, Refusal, ToWorker, WorkerId};
use scheduler::lifecycle::{self, Reply};
use scheduler::Action;
use tracing::{error, info, warn};

use super::{Core, Shared, Write};

impl Core {
    /// Carries out the tile scheduler's actions.
    /// Carries out one of the tile scheduler's actions.
    pub(super) fn apply_tiles(&mut self, sh: &Arc<Shared>, action: Action) {
        {
            match action {
                Action::SendScene { worker, job } => {
                    if let Some(scene) = self.jobs.get(&job).and_then(|r| r.scene.clone()) {
                        let record = &self.jobs[&job];
                        let message = ToWorker::Scene {
                            hash: record.hash,
                            scene: scene.to_string(),
                            assets: record.assets.to_vec(),
                        };
                        self.send(worker, message);
                    }
                }
                Action::Assign { worker, job, tile } => self.assign(sh, worker, job, tile),
                Action::CancelOnWorker { worker, job } => {
                    self.send(worker, ToWorker::Cancel { job });
                    if let Some(w) = self.workers.get_mut(&worker) {
                        w.assigned.retain(|(j, _), _| *j != job);
                    }
                }
                Action::ForgetScene { worker, scene } => {
                    self.send(worker, ToWorker::ForgetScene { hash: scene })
                }
                Action::AcceptTile { .. }
                | Action::DuplicateResult { .. }
                | Action::HoldResult { .. } => {}
                Action::AcceptHeld { job, tile } => {
                    if let Some(held) = self.held.remove(&(job, tile)) {
                        info!(job, tile, machine = %held.machine, "no other machine may confirm the audited tile: accepted as checked");
                        sh.metrics.tile_accepted(held.cost.rays, None);
                        self.accept_tile(
                            sh,
                            held.worker,
                            &held.machine,
                            job,
                            tile,
                            held.pixels,
                            &held.cost,
                            held.answer,
                        );
                    }
                }
                Action::WorkerUnresponsive { worker, silent } => {
                    if let Some(w) = self.workers.get(&worker) {
                        warn!(
                            worker,
                            name = %w.name,
                            silent_ms = silent,
                            "worker unresponsive: its leases ran out and no result came; its \
                             tiles go to other workers until it returns one"
                        );
                    }
                }
                Action::WorkerResponsive { worker } => {
                    if let Some(w) = self.workers.get(&worker) {
                        info!(worker, name = %w.name, "worker responsive again");
                    }
                }
                Action::DropWorker { worker } => {
                    if let Some(w) = self.workers.get(&worker) {
                        warn!(worker, name = %w.name, "no heartbeat in time: dropping the worker");
                    }
                    self.worker_lost(sh, worker, "no heartbeat in time (timed out)", true);
                }
                // The core has made the image due, or (a job in passes) asks for the
                // pass to be added up next.
                Action::JobDone { job } => {
                    self.held.retain(|(j, _), _| *j != job);
                }
                Action::JobFailed { job, message } => {
                    self.held.retain(|(j, _), _| *j != job);
                    warn!(job, error = %message, "job failed");
                }
            }
        }
    }

    fn send(&self, worker: WorkerId, message: ToWorker) {
        if let Some(w) = self.workers.get(&worker) {
            // A closed channel means the worker is leaving; WorkerLeft follows.
            let _ = w.outbox.send(message);
        }
    }

    fn assign(&mut self, sh: &Arc<Shared>, worker: WorkerId, job: JobId, tile: u32) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(&rect) = record.tiles.get(tile as usize) else {
            return;
        };
        let pass = self.farm.pass_run(job).map(|r| (r.pass(), r.rung()));
        let message = match (&record.adaptive, pass) {
            (Some(ad), Some((pass, rung))) => ToWorker::Advance {
                job,
                tile,
                scene: record.hash,
                frame: record.frame,
                settings: record.settings,
                rect,
                pass,
                rung,
                previous: ad.tiles[tile as usize]
                    .previous
                    .as_ref()
                    .map(|p| p.to_vec()),
            },
            _ => ToWorker::Render {
                job,
                tile,
                scene: record.hash,
                frame: record.frame,
                settings: record.settings,
                rect,
            },
        };
        if record.running_since.is_none() {
            record.running_since = Some(self.now.unix_ms);
        }
        let first = record.times.started.is_none();
        if first {
            let at = record.running_since.unwrap_or(self.now.unix_ms);
            record.times.started = Some(at);
            // The wait of this run: since the submission, or the retry.
            let queued = at.saturating_sub(
                record
                    .times
                    .retried
                    .or(record.times.submitted)
                    .unwrap_or(at),
            );
            // The event is queued before the start it tells of: the two are committed
            // one after the other, and a coordinator killed between them then logs a
            // second `started` on its restart, rather than none at all (a start
            // recorded without its event is never logged again).
            self.log(
                sh,
                job,
                "started",
                format!(
                    "first tile out after {:.1} s in the queue",
                    queued as f64 / 1000.0
                ),
            );
            self.store(
                sh,
                job,
                Write::Started {
                    job,
                    at_unix_ms: at,
                },
            );
        }
        self.send(worker, message);
        let name = match self.workers.get_mut(&worker) {
            Some(w) => {
                w.assigned.insert((job, tile), self.now.instant);
                w.name.clone()
            }
            None => format!("worker {worker}"),
        };
        self.log(sh, job, "tile_assigned", format!("tile {tile} to {name}"));
    }

    /// Carries out one of the lifecycle's actions; returns the reply it carries, if it
    /// is one.
    pub(super) fn apply_life(
        &mut self,
        sh: &Arc<Shared>,
        action: lifecycle::Action,
    ) -> Option<Result<Reply, Refusal>> {
        use lifecycle::Action as A;
        {
            match action {
                A::Acknowledge { job } => self.acknowledge(job),
                A::RefuseStored { job, message } => {
                    // A frame job's frame waits again: the core saw to it.
                    self.jobs.remove(&job);
                    sh.depot.release(job, self.now.unix_ms);
                    error!(job, error = %message, "cannot store a job");
                    if let Some(reply) = self.submits.remove(&job) {
                        let _ = reply.send(ClientResponse::Error(Refusal::internal(format!(
                            "the coordinator cannot store new jobs now: {message}"
                        ))));
                    }
                }
                A::StoreImage { job } => self.store_image(sh, job),
                // The core withdraws the tiles from the scheduler.
                A::CancelTiles { job } => self.held.retain(|(j, _), _| *j != job),
                A::RecordEnd { job, state, error } => self.record_end(sh, job, state, error),
                A::DeleteStored { job } => {
                    let shared = Arc::clone(sh);
                    self.store(
                        sh,
                        job,
                        Write::Delete {
                            job,
                            place: self.image_place(job),
                            then: Box::new(move |_| {
                                let mut core = shared.lock();
                                core.announce_job(&shared, job, "deleted", serde_json::json!({}));
                                core.jobs.remove(&job);
                                core.life_event(&shared, lifecycle::Event::Deleted { job });
                                let now = core.now.unix_ms;
                                drop(core);
                                // Its scene's files go once no other job names them.
                                shared.depot.release(job, now);
                                info!(job, "job deleted");
                                shared.changed();
                            }),
                        },
                    );
                }
                A::Reply { result, .. } => return Some(result),
            }
        }
        None
    }

    /// The job's row is written: the client hears its id; the core hands its tiles out
    /// next.
    fn acknowledge(&mut self, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        record.image = Some(render::Image::black(
            record.settings.width,
            record.settings.height,
        ));
        let tiles = record.tiles_total;
        let s = record.settings;
        info!(
            job,
            width = s.width,
            height = s.height,
            aa = s.aa,
            sampler = s.sampling.name(),
            target_error = ?s.sampling.target_error(),
            tiles,
            "job accepted"
        );
        if let Some(reply) = self.submits.remove(&job) {
            let _ = reply.send(ClientResponse::Submitted { job });
        }
    }

    /// Every tile is in: encode and store the image on the blocking pool; the
    /// lifecycle hears when it is stored.
    fn store_image(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(image) = record.image.take() else {
            error!(job, "no frame to store");
            return;
        };
        let ended = self.now.unix_ms;
        record.times.ended = Some(ended);
        if record.interactive {
            // Its tiles went to the view's page as they came: nothing to encode or keep.
            drop(image);
            let shared = Arc::clone(sh);
            drop(sh.runtime.spawn_blocking(move || {
                let event = lifecycle::Event::ImageStored {
                    job,
                    result: Ok(()),
                };
                shared.lock().life_event(&shared, event);
            }));
            return;
        }
        let meta = record.metadata(job, ended);
        let scene = record.scene.clone().unwrap_or_else(|| Arc::from(""));
        // An adaptive job keeps its tiles' final states beside its image: a refinement
        // goes on from them. They are at the last pass's rung (at or past the image's).
        let rung = self.farm.pass_run(job).map(|r| r.rung());
        let states = record.adaptive.as_ref().zip(rung).and_then(|(ad, rung)| {
            let states: Option<Vec<Arc<Vec<u8>>>> =
                ad.tiles.iter().map(|t| t.state.clone()).collect();
            Some(Box::new(crate::store::TileStates {
                rung,
                aa: record.settings.aa,
                tile_size: record.tile_size,
                states: states?,
            }))
        });
        let place = self.image_place(job);
        let shared = Arc::clone(sh);
        sh.runtime.spawn_blocking(move || {
            let png = image.to_png();
            drop(image);
            let then_shared = Arc::clone(&shared);
            shared.persistence.write(Write::Image {
                place,
                meta: Box::new(meta),
                scene,
                png,
                states,
                then: Box::new(move |result| {
                    let sh = then_shared;
                    let mut core = sh.lock();
                    if let (Ok(sha), Some(record)) = (&result, core.jobs.get_mut(&job)) {
                        record.image_sha256 = Some(*sha);
                    }
                    core.life_event(
                        &sh,
                        lifecycle::Event::ImageStored {
                            job,
                            result: result.map(|_| ()),
                        },
                    );
                }),
            });
        });
    }

    /// The job ended: free what it held and write its end.
    fn record_end(&mut self, sh: &Arc<Shared>, job: JobId, state: JobState, error: Option<String>) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        record.image = None;
        record.scene = None;
        record.tiles = Vec::new();
        record.accepted = HashMap::new();
        record.adaptive = None;
        let ended = *record.times.ended.get_or_insert(self.now.unix_ms);
        let rays = record.totals.rays;
        match state {
            JobState::Done => info!(
                job,
                wall_ms = ended.saturating_sub(record.times.submitted.unwrap_or(ended)),
                rays,
                "job done"
            ),
            JobState::Cancelled => info!(job, "job cancelled"),
            _ => {}
        }
        let queued = record
            .times
            .started
            .map(|s| s.saturating_sub(record.times.submitted.unwrap_or(s)));
        let detail = match (state, &error) {
            (JobState::Done, _) => format!(
                "{} rays, rendered in {:.1} s after {:.1} s in the queue",
                rays,
                ended.saturating_sub(record.times.started.unwrap_or(ended)) as f64 / 1000.0,
                queued.unwrap_or(0) as f64 / 1000.0
            ),
            (_, Some(e)) => e.clone(),
            (_, None) => format!(
                "{} of {} tiles done",
                record.tiles_recorded, record.tiles_total
            ),
        };
        self.log(sh, job, state.as_str(), detail);
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let shared = Arc::clone(sh);
        // A studio view's pass is forgotten once it has ended: a long drag makes many.
        let forget = record.interactive;
        if forget {
            sh.studio.ended(self.now.mono, job, state == JobState::Done);
        }
        let write = Write::End {
            job,
            state,
            error,
            totals: record.totals,
            times: record.times,
            image_sha256: record.image_sha256,
            stopped_on_time_limit: record.stopped_on_time_limit,
            then: Box::new(move |_| {
                let mut core = shared.lock();
                core.life_event(&shared, lifecycle::Event::EndRecorded { job });
                if forget {
                    core.life_event(&shared, lifecycle::Event::Delete { job });
                }
                drop(core);
                shared.changed();
            }),
        };
        self.store(sh, job, write);
    }
}
