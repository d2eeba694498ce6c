//! A machine caught returning wrong pixels: it gets no tile again, and what it
//! rendered in jobs still active is rendered again.

use std::sync::Arc;

use protocol::JobId;
use scheduler::lifecycle::Phase;
use scheduler::Event;
use tracing::{error, warn};

use super::records::rect_pixels;
use super::{Core, Shared, Write};
use crate::server::adaptive;

impl Core {
    /// The machine returned wrong pixels for a tile of job `caught_in` (said in
    /// `reason`, for people): it gets no tile again, its held results are dropped, and
    /// the tiles it rendered in active jobs are rendered again. The events of
    /// `caught_in` and of every job it had tiles in say so.
    pub fn quarantine(
        &mut self,
        sh: &Arc<Shared>,
        machine: &str,
        caught_in: JobId,
        reason: String,
    ) {
        sh.metrics.result_rejected();
        let first = !self.quarantined.contains_key(machine);
        error!(machine, reason = %reason, "quarantined");
        if first {
            sh.metrics.worker_quarantined();
            self.quarantined.insert(machine.to_string(), reason.clone());
        }
        for w in self.workers.values_mut().filter(|w| w.name == machine) {
            w.quarantined.get_or_insert_with(|| reason.clone());
        }
        self.held.retain(|_, h| h.machine != machine);
        let adaptive: Vec<JobId> = self
            .jobs
            .iter()
            .filter(|(_, r)| r.adaptive.is_some())
            .map(|(&j, _)| j)
            .collect();
        for job in adaptive {
            if !self.take_back_adaptive(sh, job, machine) {
                error!(
                    job,
                    machine,
                    "a finished adaptive job holds tiles of a quarantined machine: submit it again"
                );
            }
        }
        let mut revoke = Vec::new();
        let mut affected = Vec::new();
        for (&job, record) in &mut self.jobs {
            let tiles: Vec<u32> = record
                .accepted
                .iter()
                .filter(|(_, a)| &*a.machine == machine)
                .map(|(&t, _)| t)
                .collect();
            if tiles.is_empty() {
                continue;
            }
            if !self.farm.tiles().is_active(job) {
                // Too late to take back: the image is stored or being stored.
                error!(
                    job,
                    machine,
                    tiles = tiles.len(),
                    "a finished job holds tiles of a quarantined machine: submit it again"
                );
                continue;
            }
            for &tile in &tiles {
                if let Some(a) = record.accepted.remove(&tile) {
                    record.remove_cost(&a, rect_pixels(record.tiles[tile as usize]));
                }
                revoke.push((job, tile));
            }
            record.tiles_recorded = record.tiles_recorded.saturating_sub(tiles.len() as u32);
            if let Some(count) = record.tiles_per_worker.get_mut(machine) {
                *count = count.saturating_sub(tiles.len() as u64);
            }
            warn!(
                job,
                machine,
                tiles = tiles.len(),
                "rendering again the tiles of a quarantined machine"
            );
            affected.push((job, tiles.clone()));
            sh.persistence.write(Write::ForgetTiles { job, tiles });
        }
        // The job of its wrong tile, and those whose tiles it had rendered.
        let mut jobs: Vec<JobId> = Some(caught_in)
            .filter(|j| self.jobs.contains_key(j))
            .into_iter()
            .collect();
        jobs.extend(affected.iter().map(|(j, _)| *j));
        jobs.sort_unstable();
        jobs.dedup();
        for job in jobs {
            let taken = affected
                .iter()
                .find(|(j, _)| *j == job)
                .map_or(String::new(), |(_, t)| {
                    format!("; {} of its tiles taken back: {t:?}", t.len())
                });
            self.log(
                sh,
                job,
                "quarantine",
                format!("machine {machine} quarantined: {reason}{taken}"),
            );
        }
        self.tiles_event(
            sh,
            Event::Quarantine {
                machine: machine.to_string(),
                revoke,
            },
        );
    }

    /// A machine of the quarantine built some of an adaptive job's tiles: they start
    /// again from nothing, and the pass under way starts again under a new number (at
    /// the same rung), so that no answer built on its states counts and every rung is
    /// added up again. `false` when the job is past its passes.
    fn take_back_adaptive(&mut self, sh: &Arc<Shared>, job: JobId, machine: &str) -> bool {
        let Some(record) = self.jobs.get_mut(&job) else {
            return false;
        };
        let Some(ad) = record.adaptive.as_mut() else {
            return false;
        };
        let tainted: Vec<usize> = (0..ad.tiles.len())
            .filter(|&t| ad.tiles[t].machines.iter().any(|m| &**m == machine))
            .collect();
        if tainted.is_empty() {
            return true;
        }
        let passing = self
            .farm
            .lifecycle()
            .job(job)
            .is_some_and(|j| matches!(j.phase, Phase::Queued | Phase::Running));
        if !passing {
            return false;
        }
        warn!(
            job,
            machine,
            tiles = tainted.len(),
            "rendering again the adaptive tiles a quarantined machine built"
        );
        for t in tainted {
            ad.tiles[t] = adaptive::AdaptiveTile {
                next_work: Some(0),
                ..adaptive::AdaptiveTile::default()
            };
        }
        ad.passes.restart_pass();
        ad.evaluating = false;
        self.held.retain(|(j, _), _| *j != job);
        self.tiles_event(sh, Event::CancelJob { job });
        self.start_pass(sh, job);
        true
    }
}
