//! A machine caught returning wrong pixels: it gets no tile again, and what it
//! rendered in jobs still active is rendered again.

use std::sync::Arc;

use protocol::JobId;
use scheduler::farm::{Effect, Input};
use tracing::{error, warn};

use super::records::rect_pixels;
use super::{Core, Shared, Write};

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
            self.take_back_adaptive(sh, job, machine);
        }
        // Too late to take back from a finished job: its image is stored or being
        // stored.
        for (&job, record) in &self.jobs {
            let tiles = record
                .accepted
                .values()
                .filter(|a| &*a.machine == machine)
                .count();
            if tiles > 0 && !self.farm.tiles().is_active(job) {
                error!(
                    job,
                    machine,
                    tiles,
                    "a finished job holds tiles of a quarantined machine: submit it again"
                );
            }
        }
        let input = Input::Quarantine {
            machine: machine.to_string(),
        };
        let effects = self.farm.handle(self.now.mono, input);
        let affected: Vec<(JobId, Vec<u32>)> = effects
            .iter()
            .filter_map(|e| match e {
                Effect::TakenBack { job, tiles } => Some((*job, tiles.clone())),
                _ => None,
            })
            .collect();
        self.carry_out(sh, effects);
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
    }

    /// Tiles of an active job accepted from a quarantined machine, taken back by the
    /// core: their cost no longer counts, their stored pixels are forgotten, and they
    /// go out again.
    pub(super) fn taken_back(&mut self, sh: &Shared, job: JobId, tiles: Vec<u32>) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let mut machines: Vec<std::sync::Arc<str>> = Vec::new();
        for &tile in &tiles {
            if let Some(a) = record.accepted.remove(&tile) {
                record.remove_cost(&a, rect_pixels(record.tiles[tile as usize]));
                machines.push(a.machine);
            }
        }
        record.tiles_recorded = record.tiles_recorded.saturating_sub(machines.len() as u32);
        for machine in &machines {
            if let Some(count) = record.tiles_per_worker.get_mut(&**machine) {
                *count = count.saturating_sub(1);
            }
        }
        warn!(
            job,
            tiles = tiles.len(),
            "rendering again the tiles of a quarantined machine"
        );
        sh.persistence.write(Write::ForgetTiles { job, tiles });
    }
}
