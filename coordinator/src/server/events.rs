//! The farm's event stream in the daemon (docs/events.md): what the core announces,
//! the hub that carries recorded events to the streams, and what the HTTP side reads.
//!
//! An event goes: the core announces it under its lock ([`Core::announce`], a queued
//! write, never waited for), the persistence thread records it with the next batch and
//! gives it its id, and once that batch is committed the hook publishes it here
//! ([`Hub::publish`]) to every stream subscribed. Streamed only once durable, an event
//! a client has seen survives a `kill -9`, and its id is never given again.

use std::sync::Arc;

use protocol::{JobId, WorkerId};
use serde_json::{json, Map, Value};
use tokio::sync::broadcast;

use super::core::Core;
use super::persistence::Write;
use super::{Observer, Shared};
use crate::events::{self, Announcement, FarmEvent, FarmPage};

/// The recorded events on their way to the streams: one bounded buffer for all of
/// them ([`events::LIVE_BUFFER`]), which a slow stream falls behind in rather than
/// making it grow.
pub struct Hub {
    live: broadcast::Sender<Arc<FarmEvent>>,
}

impl Default for Hub {
    fn default() -> Self {
        Hub {
            live: broadcast::channel(events::LIVE_BUFFER).0,
        }
    }
}

impl Hub {
    /// Passes recorded events, in id order, to the streams subscribed (none: dropped,
    /// they are in the database).
    pub fn publish(&self, recorded: Vec<FarmEvent>) {
        for event in recorded {
            let _ = self.live.send(Arc::new(event));
        }
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Arc<FarmEvent>> {
        self.live.subscribe()
    }
}

impl Observer {
    /// The events recorded from now on. Subscribe before replaying from the database
    /// ([`Observer::farm_events_after`]): see [`events::Cursor`].
    pub fn subscribe_events(&self) -> broadcast::Receiver<Arc<FarmEvent>> {
        self.shared.events.subscribe()
    }

    /// The recorded events after `after`, at most `limit`, and the oldest id kept:
    /// read by the persistence thread between its writes.
    pub async fn farm_events_after(&self, after: u64, limit: usize) -> Result<FarmPage, String> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.shared.persistence.write(Write::ReadFarmEvents {
            after,
            limit,
            then: Box::new(move |page| {
                let _ = tx.send(page);
            }),
        });
        rx.await
            .unwrap_or_else(|_| Err("the coordinator is shutting down".into()))
    }
}

/// Details as a JSON object.
fn object(value: Value) -> Map<String, Value> {
    match value {
        Value::Object(map) => map,
        _ => Map::new(),
    }
}

impl Core {
    /// Queues a farm event for the disk, from where it is streamed once recorded.
    pub fn announce(&self, sh: &Shared, announcement: Announcement) {
        sh.persistence.write(Write::Announce(announcement));
    }

    /// The job or sequence `job`'s name, if it is one the farm's stream tells of: not
    /// a studio view's pass (nothing of it is kept), not a sequence's frame job (its
    /// sequence tells of its frames).
    fn announced_job_name(&self, job: JobId) -> Option<String> {
        match (self.jobs.get(&job), self.sequences.get(&job)) {
            (Some(r), _) if !r.interactive && r.sequence.is_none() => Some(r.label.name.clone()),
            (None, Some(s)) => Some(s.label.name.clone()),
            _ => None,
        }
    }

    /// An entry of `job`'s log (`kind`, `detail`) goes on the farm's stream too, if its
    /// kind is one of the stream's ([`events::JOB_KINDS`]).
    pub(super) fn announce_logged(&self, sh: &Shared, job: JobId, kind: &str, detail: &str) {
        if !events::JOB_KINDS.contains(&kind) {
            return;
        }
        self.announce_job(sh, job, kind, json!({ "detail": detail }));
    }

    /// A farm event about `job` with `details` (its name added), if the stream tells
    /// of it.
    pub(super) fn announce_job(&self, sh: &Shared, job: JobId, kind: &str, details: Value) {
        let Some(name) = self.announced_job_name(job) else {
            return;
        };
        let mut details = object(details);
        details.insert("name".into(), name.into());
        self.announce(sh, Announcement::job(self.now.unix_ms, kind, job, details));
    }

    /// A farm event about the connected worker `worker`, with `details` beside its id,
    /// name and host.
    pub(super) fn announce_worker(
        &self,
        sh: &Shared,
        worker: WorkerId,
        kind: &str,
        details: Value,
    ) {
        let Some(w) = self.workers.get(&worker) else {
            return;
        };
        let mut object = object(json!({
            "id": worker,
            "name": w.name,
            "host": w.host.to_string(),
        }));
        if let Value::Object(more) = details {
            object.extend(more);
        }
        self.announce(sh, Announcement::worker(self.now.unix_ms, kind, object));
    }

    /// A farm event about a machine by name (disabled, enabled, quarantined: a
    /// machine, which may not be connected).
    pub(super) fn announce_machine(&self, sh: &Shared, machine: &str, kind: &str, details: Value) {
        let mut object = object(json!({ "name": machine }));
        if let Value::Object(more) = details {
            object.extend(more);
        }
        self.announce(sh, Announcement::worker(self.now.unix_ms, kind, object));
    }
}
