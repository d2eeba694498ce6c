//! A machine caught returning wrong pixels: it gets no tile again, and what it
//! rendered in jobs still active is rendered again.

use std::sync::Arc;

use protocol::JobId;
use scheduler::farm::Input;
use tracing::{error, warn};

use super::records::rect_pixels;
use super::{Core, Shared, Write};

impl Core {
    /// The machine returned wrong pixels for a tile of job `caught_in` (said in
    /// `reason`, for people): the core quarantines it ([`Core::quarantined`] follows).
    pub fn quarantine(
        &mut self,
        sh: &Arc<Shared>,
        machine: &str,
        caught_in: JobId,
        reason: String,
    ) {
        let input = Input::Quarantine {
            machine: machine.to_string(),
            caught_in,
            reason,
        };
        self.feed(sh, input);
    }

    /// The core quarantined the machine: it gets no tile again, its held results are
    /// dropped, and jobs in passes take back what it rendered (the core took back its
    /// tiles of the other active jobs: `taken`). The events of `caught_in` and of every
    /// job it had tiles taken back from say so.
    pub(super) fn quarantined(
        &mut self,
        sh: &Arc<Shared>,
        machine: &str,
        caught_in: JobId,
        reason: &str,
        taken: &[(JobId, Vec<u32>)],
    ) {
        sh.metrics.result_rejected();
        let first = !self.quarantined.contains_key(machine);
        error!(machine, reason = %reason, "quarantined");
        if first {
            sh.metrics.worker_quarantined();
            self.quarantined
                .insert(machine.to_string(), reason.to_string());
            let details = serde_json::json!({ "reason": reason, "caught_in_job": caught_in });
            self.announce_machine(sh, machine, "quarantined", details);
        }
        for w in self.workers.values_mut().filter(|w| w.name == machine) {
            w.quarantined.get_or_insert_with(|| reason.to_string());
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
        // The job of its wrong tile, and those whose tiles it had rendered.
        let mut jobs: Vec<JobId> = Some(caught_in)
            .filter(|j| self.jobs.contains_key(j))
            .into_iter()
            .collect();
        jobs.extend(taken.iter().map(|(j, _)| *j));
        jobs.sort_unstable();
        jobs.dedup();
        for job in jobs {
            let taken = taken
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
