//! What a run measured: the scheduler's heap per job, tile and worker (probed on a
//! scheduler of its own), the lower bound on the makespan, and the report assembled
//! at the end. Read after the run or beside it, never during it.

use std::time::Duration;

use protocol::{JobId, WorkerId};

use super::{
    live_bytes, micros, scene_of, EventCost, Life, Memory, Sim, SimReport, EVENT_KINDS, MS,
};
use crate::tiles::{Event, Scheduler};

impl Sim<'_> {
    /// The scheduler's heap per job and per worker, measured on a separate scheduler as
    /// they are added: the jobs first (queued, nothing assigned), then the run's initial
    /// workers (each taking its credit of tiles), then the same workers alone on an
    /// empty scheduler.
    pub(super) fn probe_memory(&self) -> Memory {
        let cfg = self.cfg;
        let tiles = cfg.tiles_per_job();
        let threads: Vec<u32> = self.machines.iter().map(|m| m.threads).collect();
        let join = |s: &mut Scheduler| {
            for (i, &threads) in threads.iter().enumerate() {
                drop(s.handle(
                    0,
                    Event::WorkerJoined {
                        worker: i as WorkerId + 1,
                        threads,
                        machine: None,
                    },
                ));
            }
        };
        let mut s = Scheduler::with_policy(cfg.policy);
        let start = live_bytes();
        for job in 1..=cfg.jobs as JobId {
            drop(s.handle(
                0,
                Event::JobSubmitted {
                    job,
                    priority: 0,
                    scene: scene_of(job),
                    tiles,
                },
            ));
        }
        let jobs_bytes = live_bytes() - start;
        let start = live_bytes();
        join(&mut s);
        let busy_bytes = live_bytes() - start;
        let in_flight = s.tiles_in_flight();
        drop(s);
        let mut s = Scheduler::with_policy(cfg.policy);
        let start = live_bytes();
        join(&mut s);
        let idle_bytes = live_bytes() - start;
        drop(s);
        let per = |bytes: i64, n: usize| bytes as f64 / n.max(1) as f64;
        Memory {
            per_job_queued: per(jobs_bytes, cfg.jobs),
            per_tile_queued: per(jobs_bytes, cfg.jobs * tiles as usize),
            per_worker_idle: per(idle_bytes, threads.len()),
            per_worker_busy: per(busy_bytes, threads.len()),
            per_tile_in_flight: per(busy_bytes - idle_bytes, in_flight),
            tiles_in_flight_probed: in_flight as u64,
            peak_bytes: 0,
            end_bytes: 0,
        }
    }

    /// The lower bound on the makespan (see [`Outcome::ideal_ms`]).
    ///
    /// [`Outcome::ideal_ms`]: super::Outcome::ideal_ms
    fn ideal(&self) -> (f64, f64) {
        let start = self.jobs.iter().map(|j| j.sent).min().unwrap_or(0);
        // Before a job's first tile can start: its submission crosses the network, its
        // row is written, the tile crosses the network. After its last tile: the
        // result crosses the network, the image is encoded and written, the end is
        // written.
        let latency = micros(self.cfg.latency_ms);
        let before = (latency + self.row_write + latency) as f64;
        let after = (latency + self.image_encode + self.image_write + self.row_write) as f64;
        let first = start as f64 + before;
        let work: f64 = self
            .jobs
            .iter()
            .flat_map(|j| &j.costs)
            .map(|&c| c as f64)
            .sum();
        let mut changes = self.capacity.clone();
        changes.sort_by_key(|c| c.0);
        let mut capacity = 0.0;
        let mut i = 0;
        while i < changes.len() && changes[i].0 as f64 <= first {
            capacity += changes[i].1;
            i += 1;
        }
        let (mut t, mut done) = (first, 0.0);
        let mut work_bound = f64::INFINITY;
        loop {
            let next = changes.get(i).map_or(f64::INFINITY, |c| c.0 as f64);
            if capacity > 1e-9 && done + capacity * (next - t) >= work {
                work_bound = t + (work - done) / capacity + after;
                break;
            }
            if next.is_infinite() {
                break;
            }
            done += capacity.max(0.0) * (next - t);
            t = next;
            capacity += changes[i].1;
            i += 1;
        }
        let fastest = self
            .machines
            .iter()
            .filter(|m| m.life != Life::Off)
            .map(|m| m.speed)
            .fold(0.0, f64::max);
        let tile_bound = self
            .jobs
            .iter()
            .map(|j| {
                let longest = j.costs.iter().copied().max().unwrap_or(0) as f64;
                j.sent as f64 + before + longest / fastest + after
            })
            .fold(0.0, f64::max);
        let ms = |t: f64| (t - start as f64) / MS as f64;
        (ms(work_bound), ms(tile_bound))
    }

    pub(super) fn into_report(mut self, memory: Option<Memory>, wall: Duration) -> SimReport {
        let start = self.jobs.iter().map(|j| j.sent).min().unwrap_or(0);
        let end = if self.out.timed_out {
            self.now
        } else {
            self.jobs
                .iter()
                .filter_map(|j| j.ended)
                .max()
                .unwrap_or(self.now)
        };
        let (work_bound, tile_bound) = self.ideal();
        let out = &mut self.out;
        out.threads_initial = self
            .machines
            .iter()
            .take(self.cfg.workers)
            .map(|m| u64::from(m.threads))
            .sum();
        out.tiles = self.jobs.iter().map(|j| j.costs.len() as u64).sum();
        out.work_ms = self
            .jobs
            .iter()
            .flat_map(|j| &j.costs)
            .map(|&c| c as f64 / MS as f64)
            .sum();
        out.makespan_ms = (end - start) as f64 / MS as f64;
        out.ideal_work_ms = work_bound;
        out.ideal_tile_ms = tile_bound;
        out.ideal_ms = work_bound.max(tile_bound);
        out.efficiency = if out.makespan_ms > 0.0 && out.ideal_ms.is_finite() {
            out.ideal_ms / out.makespan_ms
        } else {
            0.0
        };
        out.workers_at_end = self
            .machines
            .iter()
            .filter(|m| m.life == Life::Running || m.life == Life::Frozen)
            .count();
        out.events = self.core.costs.iter().map(|c| c.count).sum::<u64>() + self.core.job_calls();
        if self.writer.down {
            out.storage_unavailable_ms += (self.now - self.writer.down_since) as f64 / MS as f64;
        }
        let memory = memory.map(|m| Memory {
            peak_bytes: self.core.peak,
            end_bytes: self.core.bytes,
            ..m
        });
        let core = &self.core;
        let costs: Vec<EventCost> = EVENT_KINDS
            .iter()
            .zip(core.costs)
            .filter(|(_, c)| c.count > 0)
            .map(|(kind, c)| c.report(kind))
            .chain(std::iter::once(core.admit.report("admit")).filter(|c| c.count > 0))
            .chain(core.job_costs.iter().map(|(kind, c)| c.report(kind)))
            .collect();
        SimReport {
            outcome: self.out,
            memory,
            handle_time: costs.iter().map(|c| c.total).sum(),
            by_event: costs,
            wall,
        }
    }
}
