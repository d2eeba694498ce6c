//! The jobs' side: the frames a run renders (the cost of each tile), the clients that
//! submit them and submit again when refused, and what the daemon does with the
//! lifecycle's actions until a job's end is written. The workload and its clients,
//! apart from the farm that renders it.

use protocol::{JobId, JobState, SceneHash};

use super::{Ev, Micros, Rng, Sim, SimConfig, SimPasses, Write, MS};
use crate::farm::TilePlan;
use crate::lifecycle;

pub(super) struct SimJob {
    /// Reference-thread microseconds per tile.
    pub(super) costs: Vec<Micros>,
    /// When its client first sent it.
    pub(super) sent: Micros,
    /// The lifecycle's id, once admitted (a new one after a failed insert).
    pub(super) id: Option<JobId>,
    pub(super) accepted: Vec<u8>,
    pub(super) assigned: Vec<u16>,
    /// When each tile was last sent out.
    pub(super) last_sent: Vec<Micros>,
    /// Whether a tile went out (its start is written then).
    pub(super) started: bool,
    /// When the tile scheduler reported it done or failed.
    pub(super) tiles_ended: Option<Micros>,
    /// When its end was written.
    pub(super) ended: Option<Micros>,
    /// A job rendered in passes: each tile's rung.
    pub(super) passes: Option<SimPasses>,
}

impl Sim<'_> {
    /// A submission reaches the coordinator: the lifecycle admits it (and its row is
    /// queued for writing) or refuses it (and the client submits it again later).
    pub(super) fn submit(&mut self, slot: usize) {
        if self.jobs[slot].id.is_some() {
            self.out.model_mismatches += 1;
            return;
        }
        let plan = TilePlan {
            priority: 0,
            scene: scene_of(slot as JobId),
            tiles: self.jobs[slot].costs.len() as u32,
            interactive: false,
        };
        match self.core.admit(self.now / MS, &self.cfg.request(), plan) {
            Ok(job) => {
                let i = job as usize;
                if self.by_id.len() <= i {
                    self.by_id.resize(i + 1, usize::MAX);
                }
                if self.by_id[i] != usize::MAX {
                    // An id given twice.
                    self.out.model_mismatches += 1;
                }
                self.by_id[i] = slot;
                self.jobs[slot].id = Some(job);
                if let Some(p) = self.jobs[slot].passes.as_mut() {
                    *p = SimPasses::new(p.reached.len());
                    self.core.core.start_passes(job, SimPasses::passes());
                }
                self.out.jobs_admitted += 1;
                self.persist(Write::Insert(job));
            }
            Err(_) => {
                self.out.admissions_refused += 1;
                self.resubmit(slot);
            }
        }
    }

    /// The client hears its submission was refused, waits, and submits it again.
    fn resubmit(&mut self, slot: usize) {
        let answer = self.latency();
        let again = self.latency();
        let at = self.now + answer + self.cfg.resubmit_ms * MS + again;
        self.agenda.push(at, Ev::Submit { job: slot });
    }

    /// Carries out one of the lifecycle's actions as the daemon does.
    pub(super) fn apply_life(&mut self, action: lifecycle::Action) {
        use lifecycle::Action as A;
        match action {
            // The core hands its tiles out next.
            A::Acknowledge { job } => {
                let j = &self.jobs[self.slot(job)];
                let waited = (self.now - j.sent) as f64 / MS as f64;
                self.out.jobs_acknowledged += 1;
                self.out.longest_admission_ms = self.out.longest_admission_ms.max(waited);
            }
            A::RefuseStored { job, .. } => {
                let slot = self.slot(job);
                self.by_id[job as usize] = usize::MAX;
                self.jobs[slot].id = None;
                self.out.stores_refused += 1;
                self.resubmit(slot);
            }
            A::StoreImage { job } => {
                self.agenda
                    .push(self.now + self.image_encode, Ev::ImageEncoded { job });
            }
            // The core has withdrawn them.
            A::CancelTiles { .. } => {}
            A::RecordEnd { job, state, error } => {
                if state == JobState::Failed {
                    self.out.job_failures.push((job, error.unwrap_or_default()));
                }
                self.persist(Write::End(job));
            }
            A::DeleteStored { job } => self.persist(Write::Delete(job)),
            // Nobody cancels or deletes: no client waits for a reply.
            A::Reply { .. } => {}
        }
    }

    /// A job's end is written: it is over for the farm, and `Done` for its client if
    /// the lifecycle says so.
    pub(super) fn end_recorded(&mut self, job: JobId) {
        self.life(lifecycle::Event::EndRecorded { job });
        let state = self
            .core
            .core
            .lifecycle()
            .job(job)
            .map(|j| j.phase.visible());
        let now = self.now;
        let slot = self.slot(job);
        let j = &mut self.jobs[slot];
        if j.ended.is_some() {
            self.out.model_mismatches += 1;
            return;
        }
        j.ended = Some(now);
        self.jobs_open -= 1;
        match state {
            Some(JobState::Done) => {
                self.out.jobs_done += 1;
                let last_tile = j.tiles_ended.unwrap_or(now);
                let finish = (now - last_tile) as f64 / MS as f64;
                self.out.longest_finish_ms = self.out.longest_finish_ms.max(finish);
            }
            Some(JobState::Failed) => self.out.jobs_failed += 1,
            // Nobody cancels: an end written must be done or failed.
            _ => self.out.model_mismatches += 1,
        }
    }
}

/// A distinct scene per job (each frame of an animation is its own scene).
pub(super) fn scene_of(job: JobId) -> SceneHash {
    let mut hash = [0u8; 32];
    hash[..8].copy_from_slice(&job.to_le_bytes());
    hash
}

/// The cost of each tile of a frame, in reference-thread microseconds, row by row like
/// the renderer's cut.
pub(super) fn tile_costs(cfg: &SimConfig, rng: &mut Rng) -> Vec<Micros> {
    let (w, h, side) = (
        f64::from(cfg.width),
        f64::from(cfg.height),
        f64::from(cfg.tile_size),
    );
    let small = w.min(h);
    let spots: Vec<(f64, f64, f64)> = (0..cfg.hotspots)
        .map(|_| {
            (
                rng.range(0.0, w),
                rng.range(0.0, h),
                rng.range(0.05, 0.2) * small,
            )
        })
        .collect();
    let mut costs = Vec::with_capacity(cfg.tiles_per_job() as usize);
    for y in (0..cfg.height).step_by(cfg.tile_size as usize) {
        for x in (0..cfg.width).step_by(cfg.tile_size as usize) {
            let tw = f64::from(cfg.tile_size.min(cfg.width - x));
            let th = f64::from(cfg.tile_size.min(cfg.height - y));
            let (cx, cy) = (f64::from(x) + tw / 2.0, f64::from(y) + th / 2.0);
            // A smooth bump of compact support: (1 - d²/r²)² inside the radius.
            let bump = spots
                .iter()
                .map(|&(sx, sy, r)| {
                    let q = ((cx - sx) * (cx - sx) + (cy - sy) * (cy - sy)) / (r * r);
                    if q < 1.0 {
                        (1.0 - q) * (1.0 - q)
                    } else {
                        0.0
                    }
                })
                .fold(0.0, f64::max);
            let factor = (1.0 + (cfg.hotspot_factor - 1.0) * bump)
                * rng.range(1.0 - cfg.tile_noise, 1.0 + cfg.tile_noise);
            let cost = cfg.tile_ms * MS as f64 * (tw * th) / (side * side) * factor;
            costs.push((cost.round() as Micros).max(1));
        }
    }
    costs
}
