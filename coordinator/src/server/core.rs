//! The state behind the daemon's one lock: the two state machines, the data their
//! decisions are about (scenes, frames being assembled, workers' outboxes), and how
//! their actions are carried out.
//!
//! Everything here runs under the lock, so nothing here blocks: messages go to
//! per-worker channels, writes to the persistence queue, and encoding an image to the
//! blocking pool.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Instant;

use protocol::{
    ClientResponse, JobId, JobState, JobStatus, SceneHash, Settings, TileRect, ToWorker, WorkerId,
    WorkerStatus,
};
use scheduler::lifecycle::{self, Lifecycle, Phase, Reply};
use scheduler::{Action, Event, Millis, Scheduler};
use tokio::sync::{mpsc, oneshot};
use tracing::{error, info, warn};

use super::persistence::Write;
use super::{unix_ms, Shared};
use crate::db::{StoredJob, Times, Totals};
use crate::store::JobMetadata;
use crate::tiling;

/// The state machines and their data.
pub struct Core {
    pub tiles: Scheduler,
    pub lifecycle: Lifecycle,
    pub jobs: BTreeMap<JobId, JobRecord>,
    pub workers: BTreeMap<WorkerId, WorkerRecord>,
    next_worker: WorkerId,
    /// Clients waiting for their submission to be stored.
    submits: HashMap<JobId, oneshot::Sender<ClientResponse>>,
}

/// What the daemon keeps of a job beside its lifecycle.
pub struct JobRecord {
    /// The scene text, while the job is active (workers may still ask for it).
    pub scene: Option<Arc<str>>,
    pub hash: SceneHash,
    pub settings: Settings,
    pub tile_size: u32,
    /// The tiles' rectangles, while the job is active.
    pub tiles: Vec<TileRect>,
    pub tiles_total: u32,
    pub priority: i32,
    /// The frame being assembled, while the job is active: the memory a coordinator
    /// holds grows with the active jobs' pixels (3 bytes each), never with the
    /// finished ones.
    pub image: Option<render::Image>,
    /// Wall-clock times, kept across restarts.
    pub times: Times,
    /// Rendering time spent before the last restart (from its first tile handed out
    /// to its last tile recorded), and when rendering resumed in this run: the
    /// coordinator's own downtime is not rendering time.
    pub rendered_before_ms: u64,
    pub running_since: Option<u64>,
    /// Tiles written to the database: the progress reported.
    pub tiles_recorded: u32,
    pub totals: Totals,
    pub tiles_per_worker: BTreeMap<String, u64>,
    /// The SHA-256 of the stored image, once stored.
    pub image_sha256: Option<[u8; 32]>,
}

/// A connected worker.
pub struct WorkerRecord {
    pub name: String,
    /// The renderer build its hello named.
    pub build: String,
    pub threads: u32,
    pub outbox: mpsc::UnboundedSender<ToWorker>,
    /// Notified when the scheduler drops the worker: its connection is closed.
    pub dropped: Arc<tokio::sync::Notify>,
    pub connected: Instant,
    pub tiles_done: u64,
    pub rays: u64,
    /// When each tile it holds was handed to it, for the latency metric.
    pub assigned: HashMap<(JobId, u32), Instant>,
}

/// What a worker reports a tile cost.
pub struct Cost {
    pub rays: u64,
    pub samples: u64,
    pub error_sq_sum: f64,
}

/// A job admitted by the lifecycle, to be stored.
pub struct Prepared {
    pub scene: String,
    pub hash: SceneHash,
    pub settings: Settings,
    pub tile_size: u32,
    pub tiles: Vec<TileRect>,
    pub priority: i32,
    pub request: lifecycle::Request,
}

impl Core {
    pub fn new(tiles: Scheduler, lifecycle: Lifecycle) -> Core {
        Core {
            tiles,
            lifecycle,
            jobs: BTreeMap::new(),
            workers: BTreeMap::new(),
            next_worker: 1,
            submits: HashMap::new(),
        }
    }

    /// The earliest deadline of either state machine.
    pub fn next_deadline(&self) -> Option<Millis> {
        [self.tiles.next_deadline(), self.lifecycle.next_deadline()]
            .into_iter()
            .flatten()
            .min()
    }

    /// The time has come: both state machines look at their deadlines.
    pub fn timeout(&mut self, sh: &Arc<Shared>) {
        self.tiles_event(sh, Event::Timeout);
        self.life_event(sh, lifecycle::Event::Timeout);
    }

    /// Whether tiles are out or images are being stored (a shutdown waits for them).
    pub fn is_busy(&self) -> bool {
        self.tiles.tiles_in_flight() > 0
            || self
                .lifecycle
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

    pub fn tiles_event(&mut self, sh: &Arc<Shared>, event: Event) {
        let actions = self.tiles.handle(sh.now(), event);
        self.apply_tiles(sh, actions);
    }

    /// Feeds the lifecycle and carries out its actions; returns its replies to the
    /// client that caused the event.
    pub fn life_event(
        &mut self,
        sh: &Arc<Shared>,
        event: lifecycle::Event,
    ) -> Vec<Result<Reply, String>> {
        let actions = self.lifecycle.handle(sh.now(), event);
        self.apply_life(sh, actions)
    }

    /// Enters an admitted job, waiting for its row to be written; `reply` gets the
    /// answer for the client.
    pub fn admit(
        &mut self,
        sh: &Arc<Shared>,
        prepared: Prepared,
        reply: oneshot::Sender<ClientResponse>,
    ) -> Result<StoredJob, String> {
        let id = self.lifecycle.admit(sh.now(), &prepared.request)?;
        let submitted = unix_ms();
        let stored = StoredJob {
            id,
            scene: prepared.scene.clone(),
            hash: prepared.hash,
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
        };
        self.jobs.insert(
            id,
            JobRecord {
                scene: Some(Arc::from(prepared.scene)),
                hash: prepared.hash,
                settings: prepared.settings,
                tile_size: prepared.tile_size,
                tiles_total: prepared.tiles.len() as u32,
                tiles: prepared.tiles,
                priority: prepared.priority,
                image: None,
                times: stored.times,
                rendered_before_ms: 0,
                running_since: None,
                tiles_recorded: 0,
                totals: Totals::default(),
                tiles_per_worker: BTreeMap::new(),
                image_sha256: None,
            },
        );
        self.submits.insert(id, reply);
        Ok(stored)
    }

    /// Takes back a job found on disk at startup.
    pub fn restore(&mut self, sh: &Arc<Shared>, restored: super::startup::RestoredJob) {
        let stored = restored.job;
        let id = stored.id;
        let tiles = tiling::cut(&stored.settings, stored.tile_size);
        let final_state = stored.state.is_final();
        let mut record = JobRecord {
            scene: (!final_state).then(|| Arc::from(stored.scene.as_str())),
            hash: stored.hash,
            settings: stored.settings,
            tile_size: stored.tile_size,
            tiles_total: tiles.len() as u32,
            tiles: if final_state { Vec::new() } else { tiles },
            priority: stored.priority,
            image: None,
            times: Times {
                submitted: stored.times.submitted.or(Some(unix_ms())),
                ..stored.times
            },
            rendered_before_ms: 0,
            running_since: None,
            tiles_recorded: 0,
            totals: stored.totals.unwrap_or_default(),
            tiles_per_worker: BTreeMap::new(),
            image_sha256: stored.image_sha256,
        };
        if final_state {
            if stored.state == JobState::Done {
                record.tiles_recorded = record.tiles_total;
            }
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
                        .map_or(0, |ended| unix_ms().saturating_sub(ended)),
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
        for t in restored.tiles {
            let rect = record.tiles[t.tile as usize];
            image.put_rect(to_render_rect(rect), &t.rgb);
            record.tiles_recorded += 1;
            // A tile recorded by an earlier version was a grid render: aa² per pixel.
            let pixels = rect_pixels(rect);
            let aa = u64::from(stored.settings.aa);
            let samples = t.samples.unwrap_or(pixels * aa * aa);
            record.add_cost(t.rays, samples, t.error_sq_sum, pixels);
            *record.tiles_per_worker.entry(t.worker).or_default() += 1;
            done.push(t.tile);
        }
        record.image = Some(image);
        let total = record.tiles_total;
        let (priority, hash) = (record.priority, record.hash);
        info!(job = id, done = done.len(), total, "resuming job");
        self.jobs.insert(id, record);
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
        let actions = self
            .tiles
            .resume_job(sh.now(), id, priority, hash, total, &done);
        self.apply_tiles(sh, actions);
    }

    /// A worker connected: its id.
    pub fn join(&mut self, sh: &Arc<Shared>, record: WorkerRecord) -> WorkerId {
        let id = self.next_worker;
        self.next_worker += 1;
        let (threads, name) = (record.threads, record.name.clone());
        self.workers.insert(id, record);
        self.tiles_event(
            sh,
            Event::WorkerJoined {
                worker: id,
                threads,
                machine: Some(name),
            },
        );
        id
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
        match status {
            Err(reason) => {
                self.tiles_event(sh, Event::StorageUnavailable);
                self.life_event(sh, lifecycle::Event::StorageUnavailable { reason });
            }
            Ok(()) => {
                self.life_event(sh, lifecycle::Event::StorageAvailable);
                self.tiles_event(sh, Event::StorageAvailable);
            }
        }
    }

    /// A worker's result: checked against the tile it answers, then offered to the
    /// scheduler, which decides whether it is the first (kept) or a copy (compared).
    pub fn tile_done(
        &mut self,
        sh: &Arc<Shared>,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        rgb: Vec<u8>,
        cost: Cost,
    ) -> anyhow::Result<()> {
        if let Some(record) = self.jobs.get(&job) {
            if let Some(rect) = record.tiles.get(tile as usize) {
                let expected = rect.width as usize * rect.height as usize * 3;
                anyhow::ensure!(
                    rgb.len() == expected,
                    "result for tile {tile} of job {job} has {} bytes, expected {expected}",
                    rgb.len()
                );
            } else if record.image.is_some() {
                anyhow::bail!("result for tile {tile} of job {job}, which has no such tile");
            }
        }
        let actions = self
            .tiles
            .handle(sh.now(), Event::TileDone { worker, job, tile });
        let latency = self
            .workers
            .get_mut(&worker)
            .and_then(|w| w.assigned.remove(&(job, tile)))
            .map(|at| at.elapsed());
        // A result is either accepted (its pixels move on to the database) or a copy.
        let mut rgb = Some(rgb);
        for action in &actions {
            match *action {
                Action::AcceptTile { job, tile } => {
                    sh.metrics.tile_accepted(cost.rays, latency);
                    if let Some(rgb) = rgb.take() {
                        self.accept_tile(sh, worker, job, tile, rgb, &cost);
                    }
                }
                Action::DuplicateResult { job, tile } => {
                    if let Some(rgb) = &rgb {
                        self.check_duplicate(worker, job, tile, rgb);
                    }
                }
                _ => {}
            }
        }
        self.apply_tiles(sh, actions);
        Ok(())
    }

    /// A worker could not render a tile.
    pub fn tile_failed(
        &mut self,
        sh: &Arc<Shared>,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        message: String,
    ) {
        warn!(worker, job, tile, error = %message, "tile failed");
        if let Some(w) = self.workers.get_mut(&worker) {
            w.assigned.remove(&(job, tile));
        }
        let message = format!("tile {tile} failed on a worker: {message}");
        self.tiles_event(
            sh,
            Event::TileFailed {
                worker,
                job,
                tile,
                message,
            },
        );
    }

    /// A straggler's second copy of a tile must equal the accepted one: a difference
    /// would break determinism, so it is logged as an error.
    fn check_duplicate(&self, worker: WorkerId, job: JobId, tile: u32, rgb: &[u8]) {
        let Some(record) = self.jobs.get(&job) else {
            return;
        };
        let (Some(image), Some(rect)) = (&record.image, record.tiles.get(tile as usize)) else {
            return;
        };
        let row = rect.width as usize * 3;
        let same = rgb.chunks_exact(row).enumerate().all(|(r, src)| {
            let start = ((rect.y as usize + r) * image.width as usize + rect.x as usize) * 3;
            image.rgb.get(start..start + row) == Some(src)
        });
        if same {
            info!(
                worker,
                job, tile, "duplicate result equals the accepted one"
            );
        } else {
            error!(worker, job, tile, "duplicate result differs from the accepted one: rendering is not deterministic on this worker");
        }
    }

    fn accept_tile(
        &mut self,
        sh: &Shared,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        rgb: Vec<u8>,
        cost: &Cost,
    ) {
        let name = self.workers.get_mut(&worker).map(|w| {
            w.tiles_done += 1;
            w.rays += cost.rays;
            w.name.clone()
        });
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(&rect) = record.tiles.get(tile as usize) else {
            return;
        };
        if let Some(image) = record.image.as_mut() {
            image.put_rect(to_render_rect(rect), &rgb);
        }
        // An estimate that is not a sum of squares (a broken worker) counts as unknown.
        let error_sq_sum = (cost.error_sq_sum.is_finite() && cost.error_sq_sum >= 0.0)
            .then_some(cost.error_sq_sum);
        record.add_cost(cost.rays, cost.samples, error_sq_sum, rect_pixels(rect));
        let name = name.unwrap_or_default();
        *record.tiles_per_worker.entry(name.clone()).or_default() += 1;
        sh.persistence.write(Write::Tile(crate::db::TileWrite {
            job,
            tile,
            rgb,
            rays: cost.rays,
            worker: name,
            samples: cost.samples,
            error_sq_sum,
            done_ms: unix_ms(),
        }));
    }

    /// Carries out the tile scheduler's actions.
    fn apply_tiles(&mut self, sh: &Arc<Shared>, actions: Vec<Action>) {
        for action in actions {
            match action {
                Action::SendScene { worker, job } => {
                    if let Some(scene) = self.jobs.get(&job).and_then(|r| r.scene.clone()) {
                        let hash = self.jobs[&job].hash;
                        self.send(
                            worker,
                            ToWorker::Scene {
                                hash,
                                scene: scene.to_string(),
                            },
                        );
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
                Action::AcceptTile { .. } | Action::DuplicateResult { .. } => {}
                Action::DropWorker { worker } => {
                    if let Some(w) = self.workers.remove(&worker) {
                        warn!(worker, name = %w.name, "no heartbeat in time: dropping the worker");
                        w.dropped.notify_one();
                    }
                }
                Action::JobDone { job } => {
                    self.life_event(sh, lifecycle::Event::TilesComplete { job });
                }
                Action::JobFailed { job, message } => {
                    warn!(job, error = %message, "job failed");
                    self.life_event(sh, lifecycle::Event::TilesFailed { job, message });
                }
            }
        }
        sh.changed();
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
        let message = ToWorker::Render {
            job,
            tile,
            scene: record.hash,
            settings: record.settings,
            rect,
        };
        if record.running_since.is_none() {
            record.running_since = Some(unix_ms());
        }
        let first = record.times.started.is_none();
        if first {
            let at = record.running_since.unwrap_or_else(unix_ms);
            record.times.started = Some(at);
            sh.persistence.write(Write::Started {
                job,
                at_unix_ms: at,
            });
        }
        self.send(worker, message);
        if let Some(w) = self.workers.get_mut(&worker) {
            w.assigned.insert((job, tile), Instant::now());
        }
        self.life_event(sh, lifecycle::Event::TileAssigned { job });
    }

    /// Carries out the lifecycle's actions; returns its replies.
    fn apply_life(
        &mut self,
        sh: &Arc<Shared>,
        actions: Vec<lifecycle::Action>,
    ) -> Vec<Result<Reply, String>> {
        use lifecycle::Action as A;
        let mut replies = Vec::new();
        for action in actions {
            match action {
                A::Acknowledge { job } => self.acknowledge(sh, job),
                A::RefuseStored { job, message } => {
                    self.jobs.remove(&job);
                    error!(job, error = %message, "cannot store a job");
                    if let Some(reply) = self.submits.remove(&job) {
                        let _ = reply.send(ClientResponse::Error {
                            message: format!(
                                "the coordinator cannot store new jobs now: {message}"
                            ),
                        });
                    }
                }
                A::StoreImage { job } => self.store_image(sh, job),
                A::CancelTiles { job } => self.tiles_event(sh, Event::CancelJob { job }),
                A::RecordEnd { job, state, error } => self.record_end(sh, job, state, error),
                A::DeleteStored { job } => {
                    let shared = Arc::clone(sh);
                    sh.persistence.write(Write::Delete {
                        job,
                        then: Box::new(move |_| {
                            let mut core = shared.lock();
                            core.jobs.remove(&job);
                            core.life_event(&shared, lifecycle::Event::Deleted { job });
                            drop(core);
                            info!(job, "job deleted");
                            shared.changed();
                        }),
                    });
                }
                A::Reply { result, .. } => replies.push(result),
            }
        }
        sh.changed();
        replies
    }

    /// The job's row is written: the client hears its id, the tiles go out.
    fn acknowledge(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        record.image = Some(render::Image::black(
            record.settings.width,
            record.settings.height,
        ));
        let (priority, scene, tiles) = (record.priority, record.hash, record.tiles_total);
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
        self.tiles_event(
            sh,
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            },
        );
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
        let ended = unix_ms();
        record.times.ended = Some(ended);
        let meta = record.metadata(job, ended);
        let scene = record.scene.clone().unwrap_or_else(|| Arc::from(""));
        let shared = Arc::clone(sh);
        sh.runtime.spawn_blocking(move || {
            let png = image.to_png();
            drop(image);
            let then_shared = Arc::clone(&shared);
            shared.persistence.write(Write::Image {
                meta: Box::new(meta),
                scene,
                png,
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
        let ended = *record.times.ended.get_or_insert_with(unix_ms);
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
        let shared = Arc::clone(sh);
        sh.persistence.write(Write::End {
            job,
            state,
            error,
            totals: record.totals,
            times: record.times,
            image_sha256: record.image_sha256,
            then: Box::new(move |_| {
                shared
                    .lock()
                    .life_event(&shared, lifecycle::Event::EndRecorded { job });
                shared.changed();
            }),
        });
    }

    /// A client's view of a job.
    pub fn status(&self, id: JobId) -> Option<JobStatus> {
        let job = self.lifecycle.job(id)?;
        let record = self.jobs.get(&id)?;
        Some(record.status(id, job))
    }

    pub fn worker_statuses(&self) -> Vec<WorkerStatus> {
        self.workers
            .iter()
            .map(|(&id, w)| w.status(id, self.tiles.held_by(id)))
            .collect()
    }
}

fn to_render_rect(r: TileRect) -> render::Rect {
    render::Rect {
        x: r.x,
        y: r.y,
        width: r.width,
        height: r.height,
    }
}

fn rect_pixels(r: TileRect) -> u64 {
    u64::from(r.width) * u64::from(r.height)
}

impl JobRecord {
    /// Counts a tile of `pixels` pixels that took `samples` samples, with its sum of
    /// squared error estimates if known.
    fn add_cost(&mut self, rays: u64, samples: u64, error_sq_sum: Option<f64>, pixels: u64) {
        let t = &mut self.totals;
        t.rays = t.rays.saturating_add(rays);
        t.samples = t.samples.saturating_add(samples);
        if let Some(e) = error_sq_sum {
            t.error_sq_sum += e;
            t.error_pixels += pixels;
        }
    }

    /// The RMS of the per-pixel error estimates over the finished pixels that have one,
    /// in levels; `None` with one sample per pixel (no spread to measure) or before any.
    fn estimated_error(&self) -> Option<f64> {
        let t = &self.totals;
        (self.settings.aa >= 2 && t.error_pixels > 0)
            .then(|| (t.error_sq_sum / t.error_pixels as f64).sqrt())
    }

    /// Rays per second of rendering: from the first tile handed out to the end, less
    /// the time the job waited in the queue or the coordinator was down.
    fn rays_per_second(&self, until: u64) -> f64 {
        let this_run = until.saturating_sub(self.running_since.unwrap_or(until));
        let seconds = (self.rendered_before_ms + this_run) as f64 / 1000.0;
        self.totals.rays as f64 / seconds.max(1e-3)
    }

    fn metadata(&self, id: JobId, ended: u64) -> JobMetadata {
        let submitted = self.times.submitted.unwrap_or(ended);
        let s = self.settings;
        JobMetadata {
            id,
            state: "done",
            scene_sha256: hex(&self.hash),
            width: s.width,
            height: s.height,
            aa: s.aa,
            max_depth: s.max_depth,
            tile_size: self.tile_size,
            tiles: self.tiles_total,
            priority: self.priority,
            wall_time_ms: ended.saturating_sub(submitted),
            rays: self.totals.rays,
            rays_per_second: self.rays_per_second(ended),
            tiles_per_worker: self.tiles_per_worker.clone(),
            sampler: s.sampling.name(),
            target_error: s.sampling.target_error(),
            samples: self.totals.samples,
            samples_per_pixel: self.totals.samples as f64
                / (u64::from(s.width) * u64::from(s.height)).max(1) as f64,
            estimated_error: self.estimated_error(),
            submitted_unix_ms: submitted,
            started_unix_ms: self.times.started.unwrap_or(submitted),
            ended_unix_ms: ended,
            // Filled in by the store, which computes it from the bytes it writes.
            image_sha256: String::new(),
        }
    }

    fn status(&self, id: JobId, job: &lifecycle::Job) -> JobStatus {
        let state = job.phase.visible();
        let now = unix_ms();
        let end = self.times.ended.filter(|_| state.is_final()).unwrap_or(now);
        let submitted = self.times.submitted.unwrap_or(end);
        let total = self.tiles_total;
        let done = if state == JobState::Done {
            total
        } else {
            self.tiles_recorded
        };
        let eta_ms = (state == JobState::Running && done > 0 && done < total)
            .then(|| {
                let started = self.times.started?;
                let per_tile = now.saturating_sub(started) as f64 / f64::from(done);
                Some((per_tile * f64::from(total - done)) as u64)
            })
            .flatten();
        let error = match &job.phase {
            Phase::Ended { error, .. } if state.is_final() => error.clone(),
            _ => None,
        };
        JobStatus {
            id,
            state,
            settings: self.settings,
            priority: self.priority,
            tiles_done: done,
            tiles_total: total,
            rays: self.totals.rays,
            elapsed_ms: end.saturating_sub(submitted),
            eta_ms,
            error,
            samples: self.totals.samples,
            estimated_error: self.estimated_error(),
        }
    }
}

impl WorkerRecord {
    fn status(&self, id: WorkerId, in_flight: usize) -> WorkerStatus {
        let connected = self.connected.elapsed();
        WorkerStatus {
            id,
            name: self.name.clone(),
            threads: self.threads,
            tiles_in_flight: in_flight as u32,
            tiles_done: self.tiles_done,
            rays: self.rays,
            connected_ms: connected.as_millis() as u64,
            rays_per_second: self.rays as f64 / connected.as_secs_f64().max(1e-9),
            build: self.build.clone(),
            quarantined: None,
            rtt_us: None,
            credit: 2 * self.threads.max(1),
        }
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
