//! Workers joining and leaving, the leases they ran past, and their statuses.

use std::collections::HashSet;
use std::sync::Arc;

use protocol::{JobId, ToWorker, WorkerId, WorkerStatus};
use scheduler::Event;
use tracing::{info, warn};

use super::names;
use super::records::WorkerRecord;
use super::{Core, Shared};

impl Core {
    /// A worker connected: its id and the name it joins under ([`names::place`]).
    /// A connection it supersedes is told why and closed, and its tiles go back to the
    /// queue at once, as a lost worker's do.
    pub fn join(&mut self, sh: &Arc<Shared>, mut record: WorkerRecord) -> (WorkerId, String) {
        let id = self.next_worker;
        self.next_worker += 1;
        let host = record.host;
        let connected = self.workers.iter().map(|(&id, w)| names::Holder {
            id,
            name: &w.name,
            host: w.host,
        });
        let naming = names::place(connected, &record.name, host);
        match &naming {
            names::Naming::Free => {}
            names::Naming::Supersedes { name, old } => info!(
                worker = id,
                old,
                "worker {name} reconnected from {host} while its old connection (worker \
                 {old}) was open: the old connection is closed and its tiles put back"
            ),
            names::Naming::Suffixed {
                name,
                holder,
                host: held_on,
                ..
            } => warn!(
                worker = id,
                holder,
                "worker name {} is already taken by worker {holder} from {held_on}: the \
                 worker from {host} joins as {name} (give each machine its own --name)",
                record.name
            ),
        }
        if let Some(old) = naming.superseded() {
            let why = format!(
                "superseded by a new connection of worker {} from the same host ({host})",
                naming.name(&record.name)
            );
            if let Some(w) = self.workers.get(&old) {
                let _ = w.outbox.send(ToWorker::Refuse {
                    reason: format!(
                        "{why}: two workers on one machine need different names (--name)"
                    ),
                });
            }
            self.worker_lost(sh, old, &why, true);
            self.tiles_event(sh, Event::WorkerLeft { worker: old });
        }
        record.name = naming.name(&record.name).to_owned();
        let (threads, name, tags) = (record.threads, record.name.clone(), record.tags.clone());
        if let Some(reason) = self.quarantined.get(&name) {
            warn!(worker = id, %name, "a quarantined machine joined: it gets no tile");
            record.quarantined = Some(reason.clone());
        }
        // The worker logs the name it is known by (another than it asked for, when
        // suffixed).
        let _ = record.outbox.send(ToWorker::Joined { name: name.clone() });
        self.workers.insert(id, record);
        self.announce_worker(
            sh,
            id,
            "joined",
            serde_json::json!({ "threads": threads, "tags": tags }),
        );
        // Its tags first: its first tiles already follow them.
        self.tiles_event(sh, Event::WorkerTags { worker: id, tags });
        self.tiles_event(
            sh,
            Event::WorkerJoined {
                worker: id,
                threads,
                machine: Some(name.clone()),
            },
        );
        (id, name)
    }

    /// A worker is gone (it left, or missed its heartbeats: then `drop` closes its
    /// connection): the tiles it held go back to the queue, each noted in its job's
    /// log.
    pub fn worker_lost(&mut self, sh: &Shared, worker: WorkerId, why: &str, drop: bool) {
        self.announce_worker(sh, worker, "left", serde_json::json!({ "why": why }));
        let Some(w) = self.workers.remove(&worker) else {
            return;
        };
        let mut held: Vec<(JobId, u32)> = w.assigned.keys().copied().collect();
        held.sort_unstable();
        for (job, tile) in held {
            self.log(
                sh,
                job,
                "tile_taken_back",
                format!("tile {tile} from {}: {why}", w.name),
            );
        }
        if drop {
            w.dropped.drop_with(why);
        }
    }

    pub fn worker_statuses(&self) -> Vec<WorkerStatus> {
        self.workers
            .iter()
            .map(|(&id, w)| {
                let mut status = w.status(
                    id,
                    self.farm.tiles().held_by(id),
                    self.farm.tiles().credit_of(id),
                    self.now.instant,
                );
                status.disabled = self.farm.tiles().is_disabled(&w.name);
                status.unresponsive = self.farm.tiles().is_unresponsive(id);
                status
            })
            .collect()
    }

    /// Why no tile can go out to any worker, when that is so: the one line clients
    /// show while jobs wait (the scheduler decides who may take tiles).
    pub fn no_worker_warning(&self) -> Option<String> {
        if self.farm.tiles().can_hand_out() {
            return None;
        }
        let connected = self.workers.len();
        Some(if connected == 0 {
            "no worker is connected: queued and running jobs wait until one connects".into()
        } else {
            format!(
                "no worker can take tiles: all {connected} connected are disabled, draining, \
                 quarantined or unresponsive (see tessera workers)"
            )
        })
    }

    /// Logs, once each, the tiles whose worker ran past its lease: the scheduler has put
    /// them back for another worker (what the first one returns may still count). Looked
    /// for only when the scheduler's count of expired leases moved.
    pub(super) fn log_expired_leases(&mut self, sh: &Shared) {
        let count = self.farm.tiles().counters().leases_expired;
        if count == self.leases_expired_seen && self.expiries_logged.is_empty() {
            return;
        }
        self.leases_expired_seen = count;
        let now: HashSet<(JobId, u32, WorkerId)> = self
            .farm
            .tiles()
            .expired_leases()
            .into_iter()
            .map(|(job, tile, worker, out_for)| {
                if !self.expiries_logged.contains(&(job, tile, worker)) {
                    let name = self
                        .workers
                        .get(&worker)
                        .map_or_else(|| format!("worker {worker}"), |w| w.name.clone());
                    self.log(
                        sh,
                        job,
                        "tile_lease_expired",
                        format!(
                            "tile {tile} on {name} for {:.1} s, past its lease: put back for \
                             another worker (a late result still counts)",
                            out_for as f64 / 1000.0
                        ),
                    );
                }
                (job, tile, worker)
            })
            .collect();
        self.expiries_logged = now;
    }
}
