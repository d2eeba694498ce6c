//! A machine caught returning wrong pixels: it gets no tile again, and what it
//! rendered in jobs still active is rendered again.

use std::sync::Arc;

use protocol::JobId;
use scheduler::Event;
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
}
