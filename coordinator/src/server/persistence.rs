//! Persistence: the one thread that writes to the data directory.
//!
//! Every write (a new job, finished tiles, a job's start and end, an image, a
//! deletion) is queued here and carried out in order on this thread, never under the
//! daemon's state lock: a slow, full or frozen disk delays only what waits for it.
//! What the daemon must know comes back through [`Hooks`] and the callbacks of the
//! writes.
//!
//! Failures are transient until proven otherwise. A write that fails (disk full,
//! read-only filesystem, I/O error) marks storage unavailable (one log line, through
//! [`Hooks::storage`]) and is retried every [`RETRY`] on a freshly opened database,
//! in order, until it succeeds; then storage is available again, by itself. A write
//! that does not complete within [`STALL`] (a frozen or hung filesystem) marks storage
//! unavailable the same way ([`Persistence::check_stall`]), until it completes. The one
//! exception is a new job: its client is waiting, so a failed insert is answered at
//! once, and the thread then probes the disk until it can write again.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, Sender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use protocol::{JobEvent, JobId, JobState, EVENTS_PER_PAGE};
use tracing::{info, warn};

use crate::db::{Db, Durability, EventWrite, ReopenError, StoredJob, TileWrite, Times, Totals};
use crate::events::{Announcement, FarmEvent, FarmPage, Retention};
use crate::store::{ImagePlace, JobMetadata, Store};

/// How long after a failed write it is tried again.
pub const RETRY: Duration = Duration::from_millis(500);

/// A write running longer than this means the disk has stalled.
pub const STALL: Duration = Duration::from_secs(2);

/// Tiles written in one transaction at most.
/// How long tile results and event log entries wait for others to share their
/// transaction: a farm sends hundreds of tiles a second, and a sync each (the disk's
/// slowest operation) cost the coordinator a core's tenth on two cores. A tile recorded
/// this much later is at worst rendered again after a crash, which the results'
/// idempotence makes harmless.
const GROUP_COMMIT: Duration = Duration::from_millis(10);

const TILE_BATCH: usize = 256;

/// Event log entries written in one transaction at most (they are small).
const EVENT_BATCH: usize = 4096;

/// Called with a write's outcome (on the persistence thread).
pub type Then<T> = Box<dyn FnOnce(Result<T, String>) + Send>;

/// What the daemon learns from the persistence thread.
pub trait Hooks: Send + Sync {
    /// Tiles are durably recorded.
    fn tiles_recorded(&self, tiles: &[(JobId, u32)]);
    /// Storage became unavailable (`Err` with the reason) or available again.
    fn storage(&self, status: Result<(), String>);
    /// The farm's events are durably recorded, with their ids, in id order: now they
    /// may be streamed (docs/events.md).
    fn farm_events(&self, events: Vec<FarmEvent>);
}

/// One write, with what to do once it is done.
pub enum Write {
    InsertJob {
        job: Box<StoredJob>,
        then: Then<()>,
    },
    Tile(TileWrite),
    Started {
        job: JobId,
        at_unix_ms: u64,
    },
    /// Deletes tiles whose results were revoked: they are rendered again.
    ForgetTiles {
        job: JobId,
        tiles: Vec<u32>,
    },
    /// Stores the image files; `then` gets the image's checksum.
    Image {
        place: ImagePlace,
        meta: Box<JobMetadata>,
        scene: Arc<str>,
        png: Vec<u8>,
        /// An adaptive job's final tile states, kept for refinements.
        states: Option<Box<crate::store::TileStates>>,
        then: Then<[u8; 32]>,
    },
    End {
        job: JobId,
        state: JobState,
        error: Option<String>,
        totals: Totals,
        times: Times,
        image_sha256: Option<[u8; 32]>,
        /// The job ended on its time limit before meeting its target.
        stopped_on_time_limit: bool,
        then: Then<()>,
    },
    Delete {
        job: JobId,
        place: ImagePlace,
        then: Then<()>,
    },
    /// A sequence job is running again (a frame of it was requeued): its row says so,
    /// its end forgotten.
    SequenceRunning {
        job: JobId,
    },
    /// An entry of a job's event log: written with the tiles and entries queued with
    /// it, in one transaction.
    Event(EventWrite),
    /// An event of the farm's stream: recorded with the tiles and entries queued with
    /// it, in one transaction, and given its id there.
    Announce(Announcement),
    /// Reads a page of the farm's events after `after` (docs/events.md), with the
    /// oldest id kept.
    ReadFarmEvents {
        after: u64,
        limit: usize,
        then: Then<FarmPage>,
    },
    /// Reads a page of a job's event log, after every entry queued before it is
    /// written: a client reads what happened up to its request.
    ReadEvents {
        job: JobId,
        after: u64,
        then: Then<Vec<JobEvent>>,
    },
    /// Puts a failed or cancelled job back in the queue and reads it back with its
    /// stored tiles (checked as at startup); `None`: the job is gone.
    Reopen {
        job: JobId,
        then: Then<Option<super::startup::RestoredJob>>,
    },
    /// Records an operator's pause and priority of an active job.
    Controls {
        job: JobId,
        paused: bool,
        priority: i32,
        then: Then<()>,
    },
    /// Records that an operator disabled or enabled a machine.
    Disabled {
        machine: String,
        disabled: bool,
        then: Then<()>,
    },
    /// Reads the webhooks' cursors, in the order of `urls` (a new webhook's is
    /// recorded: it starts after the last farm event).
    WebhookCursors {
        urls: Vec<String>,
        then: Then<Vec<u64>>,
    },
    /// Records that a webhook settled every farm event up to `cursor`.
    WebhookCursor {
        url: String,
        cursor: u64,
    },
}

impl Write {
    /// Carries out nothing of the write, for a job nothing is kept of (a pass of a
    /// studio view, docs/studio.md): its callback, if it has one, is told it was
    /// stored. Must not run with the coordinator's lock held (callbacks take it).
    pub fn discard(self) {
        match self {
            Write::InsertJob { then, .. }
            | Write::End { then, .. }
            | Write::Delete { then, .. }
            | Write::Controls { then, .. }
            | Write::Disabled { then, .. } => then(Ok(())),
            Write::Image { then, .. } => then(Ok([0; 32])),
            Write::ReadEvents { then, .. } => then(Ok(Vec::new())),
            Write::ReadFarmEvents { then, .. } => then(Ok(FarmPage::default())),
            Write::Reopen { then, .. } => then(Ok(None)),
            Write::WebhookCursors { urls, then } => then(Ok(vec![0; urls.len()])),
            Write::WebhookCursor { .. }
            | Write::Tile(_)
            | Write::Started { .. }
            | Write::SequenceRunning { .. }
            | Write::ForgetTiles { .. }
            | Write::Event(_)
            | Write::Announce(_) => {}
        }
    }
}

/// The handle the daemon queues writes on.
pub struct Persistence {
    queue: Mutex<Option<Sender<Write>>>,
    status: Arc<Status>,
    thread: Mutex<Option<std::thread::JoinHandle<()>>>,
}

/// What the thread shows of itself to the stall check.
struct Status {
    started: Instant,
    /// When the write in progress started (ms since `started`, plus one), or 0.
    busy_since: AtomicU64,
    /// Whether storage is reported unavailable. A mutex, not an atomic: the change
    /// and its report to the daemon must be in the same order for every reporter (the
    /// thread and the stall check), or an old "unavailable" could arrive last.
    down: Mutex<bool>,
}

impl Status {
    fn is_down(&self) -> bool {
        *self.down.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn report(&self, hooks: &dyn Hooks, status: Result<(), String>) {
        let down = status.is_err();
        let mut current = self.down.lock().unwrap_or_else(|e| e.into_inner());
        if *current != down {
            *current = down;
            match &status {
                Err(reason) => warn!(
                    reason = %reason,
                    "storage unavailable: {reason}; handing out no new tiles and taking no new \
                     jobs until it recovers"
                ),
                Ok(()) => info!("storage available again: resuming"),
            }
            hooks.storage(status);
        }
    }
}

impl Persistence {
    /// Starts the thread, which owns the database.
    pub fn start(
        db: Db,
        db_path: PathBuf,
        store: Arc<Store>,
        hooks: Arc<dyn Hooks>,
        retention: Retention,
    ) -> Persistence {
        let (tx, rx) = std::sync::mpsc::channel();
        let status = Arc::new(Status {
            started: Instant::now(),
            busy_since: AtomicU64::new(0),
            down: Mutex::new(false),
        });
        let writer = Writer {
            db: Some(db),
            db_path,
            store,
            hooks,
            status: Arc::clone(&status),
            durability: Durability::Synced,
            retention,
        };
        let thread = std::thread::Builder::new()
            .name("persistence".into())
            .spawn(move || writer.run(rx))
            .expect("the system cannot start a thread");
        Persistence {
            queue: Mutex::new(Some(tx)),
            status,
            thread: Mutex::new(Some(thread)),
        }
    }

    /// Queues a write (never blocks). After [`Persistence::close`] writes are dropped.
    pub fn write(&self, write: Write) {
        if let Some(tx) = self.queue.lock().expect("queue lock").as_ref() {
            let _ = tx.send(write);
        }
    }

    /// Reports a stall if the write in progress has run past [`STALL`]. Called
    /// periodically from outside the thread, which may be stuck in the kernel.
    pub fn check_stall(&self, hooks: &dyn Hooks) {
        let since = self.status.busy_since.load(Ordering::SeqCst);
        if since == 0 {
            return;
        }
        let now = self.status.started.elapsed().as_millis() as u64 + 1;
        let busy = Duration::from_millis(now.saturating_sub(since));
        if busy >= STALL && !self.status.is_down() {
            self.status.report(
                hooks,
                Err(format!(
                    "the data directory has not completed a write for {} s (stalled)",
                    busy.as_secs()
                )),
            );
            // The write may have completed meanwhile (and found storage not yet down):
            // then storage is available again at once.
            if self.status.busy_since.load(Ordering::SeqCst) != since {
                self.status.report(hooks, Ok(()));
            }
        }
    }

    /// Stops taking writes and waits (at most `grace`) for those queued to be done.
    /// Returns whether everything was written.
    pub fn close(&self, grace: Duration) -> bool {
        self.queue.lock().expect("queue lock").take();
        let Some(thread) = self.thread.lock().expect("thread lock").take() else {
            return true;
        };
        let deadline = Instant::now() + grace;
        while !thread.is_finished() {
            if Instant::now() >= deadline {
                warn!("storage did not finish its writes in time: unwritten work is redone after a restart");
                return false;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = thread.join();
        true
    }
}

struct Writer {
    /// `None` after a failure closed it; reopened before the next attempt.
    db: Option<Db>,
    db_path: PathBuf,
    store: Arc<Store>,
    hooks: Arc<dyn Hooks>,
    status: Arc<Status>,
    /// How the step being carried out is committed.
    durability: Durability,
    /// How long and how many of the farm's events are kept.
    retention: Retention,
}

/// A write taken off the queue, with the tiles, event log entries and farm events
/// batched.
enum Step {
    Tiles(Vec<TileWrite>, Vec<EventWrite>, Vec<Announcement>),
    One(Write),
    /// Checks that the disk can be written again (after a failed insert).
    Probe,
}

impl Step {
    /// How its commit is made to last: synced when someone is told it is done.
    fn durability(&self) -> Durability {
        match self {
            // A farm event may be streamed once committed: synced, so that an id a
            // client has seen is never given again, not even after a power cut. They
            // are few (no tile has one), so the syncs are too.
            Step::Tiles(_, _, announced) if !announced.is_empty() => Durability::Synced,
            Step::One(Write::Announce(_)) => Durability::Synced,
            Step::Tiles(..)
            | Step::One(Write::Tile(_) | Write::Event(_) | Write::Started { .. }) => {
                Durability::Ordered
            }
            // Lost to a power cut, a webhook's cursor goes back: its receiver is sent
            // again what it may have had, which it deduplicates by id.
            Step::One(Write::WebhookCursor { .. }) => Durability::Ordered,
            // A sequence's frame job is started by the coordinator, not accepted from
            // anyone: lost to a power cut, it is started again.
            Step::One(Write::InsertJob { job, .. }) if job.sequence.is_some() => {
                Durability::Ordered
            }
            _ => Durability::Synced,
        }
    }
}

impl Writer {
    fn run(mut self, rx: Receiver<Write>) {
        let mut next: Option<Write> = None;
        let mut probing = false;
        loop {
            let step = if probing {
                Step::Probe
            } else {
                let owed = self.db.as_ref().and_then(Db::owed_give_back);
                let first = match (next.take(), owed) {
                    (Some(w), _) => w,
                    (None, None) => match rx.recv() {
                        Ok(w) => w,
                        Err(_) => return self.stop(),
                    },
                    // Space freed by the last ends is given back once the writes pause.
                    (None, Some(wait)) => match rx.recv_timeout(wait) {
                        Ok(w) => w,
                        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                            if let Some(db) = self.db.as_mut() {
                                db.give_back_now();
                            }
                            continue;
                        }
                        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return self.stop(),
                    },
                };
                match first {
                    first @ (Write::Tile(_) | Write::Event(_) | Write::Announce(_)) => {
                        let (mut tiles, mut events, mut announced) =
                            (Vec::new(), Vec::new(), Vec::new());
                        let mut write = first;
                        // Group commit: what comes within GROUP_COMMIT of the first
                        // goes in the same transaction, one sync for all of it.
                        let until = Instant::now() + GROUP_COMMIT;
                        loop {
                            match write {
                                Write::Tile(t) => tiles.push(t),
                                Write::Event(e) => events.push(e),
                                Write::Announce(a) => announced.push(a),
                                other => {
                                    next = Some(other);
                                    break;
                                }
                            }
                            if tiles.len() >= TILE_BATCH
                                || events.len() + announced.len() >= EVENT_BATCH
                            {
                                break;
                            }
                            let left = until.saturating_duration_since(Instant::now());
                            match rx.recv_timeout(left) {
                                Ok(w) => write = w,
                                Err(_) => break,
                            }
                        }
                        Step::Tiles(tiles, events, announced)
                    }
                    other => Step::One(other),
                }
            };
            probing = self.carry_out(step);
        }
    }

    /// The queue is closed and every write carried out: the job ids reserved and not
    /// issued are given back.
    fn stop(&self) {
        if let Err(e) = self.store.release_reserved_ids() {
            warn!(error = %one_line(&e), "cannot give back the job ids reserved and not issued");
        }
    }

    /// Carries a step out, retrying until it succeeds (but a new job's insert, which is
    /// answered at once). Returns whether the disk must now be probed.
    fn carry_out(&mut self, step: Step) -> bool {
        self.durability = step.durability();
        match step {
            Step::Probe => {
                let store = Arc::clone(&self.store);
                self.until_done(|db| db.probe().and_then(|()| store.probe()));
                false
            }
            Step::Tiles(batch, events, announced) => {
                let retention = self.retention;
                let recorded = self.until_done(|db| {
                    db.save_batch(&batch, &events, &announced, retention, super::unix_ms())
                });
                if !recorded.is_empty() {
                    self.hooks.farm_events(recorded);
                }
                if batch.is_empty() {
                    return false;
                }
                let done: Vec<(JobId, u32)> = batch.iter().map(|t| (t.job, t.tile)).collect();
                self.hooks.tiles_recorded(&done);
                false
            }
            Step::One(Write::Event(e)) => {
                self.carry_out(Step::Tiles(Vec::new(), vec![e], Vec::new()))
            }
            Step::One(Write::Announce(a)) => {
                self.carry_out(Step::Tiles(Vec::new(), Vec::new(), vec![a]))
            }
            Step::One(Write::ReadFarmEvents { after, limit, then }) => {
                // Answered at once either way, as a job's log is.
                then(self.attempt(|db| db.farm_events_after(after, limit)));
                false
            }
            Step::One(Write::WebhookCursors { urls, then }) => {
                then(self.attempt(|db| db.webhook_cursors(&urls)));
                false
            }
            Step::One(Write::WebhookCursor { url, cursor }) => {
                self.until_done(|db| db.set_webhook_cursor(&url, cursor));
                false
            }
            Step::One(Write::ReadEvents { job, after, then }) => {
                // Answered at once either way: a client waits for it, and a read that
                // fails is no reason to stop writing.
                then(self.attempt(|db| db.load_events(job, after, EVENTS_PER_PAGE)));
                false
            }
            Step::One(Write::InsertJob { job, then }) => {
                if self.status.is_down() {
                    then(Err("storage is unavailable".into()));
                    return false;
                }
                let store = Arc::clone(&self.store);
                let result = self.attempt(|db| {
                    store.record_last_id(job.id)?;
                    db.insert_job(&job)
                });
                match result {
                    Ok(()) => {
                        then(Ok(()));
                        false
                    }
                    Err(e) => {
                        then(Err(e));
                        true
                    }
                }
            }
            Step::One(Write::Tile(t)) => {
                self.carry_out(Step::Tiles(vec![t], Vec::new(), Vec::new()))
            }
            Step::One(Write::Started { job, at_unix_ms }) => {
                self.until_done(|db| db.set_started(job, at_unix_ms));
                false
            }
            Step::One(Write::ForgetTiles { job, tiles }) => {
                self.until_done(|db| db.delete_tiles(job, &tiles));
                false
            }
            Step::One(Write::Image {
                place,
                meta,
                scene,
                png,
                states,
                then,
            }) => {
                let store = Arc::clone(&self.store);
                let sha =
                    self.until_done(|_| store.save(place, &meta, &scene, &png, states.as_deref()));
                then(Ok(sha));
                false
            }
            Step::One(Write::End {
                job,
                state,
                error,
                totals,
                times,
                image_sha256,
                stopped_on_time_limit,
                then,
            }) => {
                self.until_done(|db| {
                    db.set_ended(job, state, error.as_deref(), totals, times, image_sha256)?;
                    if stopped_on_time_limit {
                        db.set_stopped_on_time_limit(job)?;
                    }
                    Ok(())
                });
                then(Ok(()));
                false
            }
            Step::One(Write::Controls {
                job,
                paused,
                priority,
                then,
            }) => {
                self.until_done(|db| db.set_controls(job, paused, priority));
                then(Ok(()));
                false
            }
            Step::One(Write::Disabled {
                machine,
                disabled,
                then,
            }) => {
                self.until_done(|db| db.set_disabled(&machine, disabled));
                then(Ok(()));
                false
            }
            Step::One(Write::Reopen { job, then }) => {
                // A row that cannot be used is the job's problem, not the disk's: it
                // is answered as such without marking storage unavailable.
                let result = self.attempt(|db| match db.reopen_job(job, super::unix_ms()) {
                    Ok(Some(stored)) => super::startup::check_job(db, stored).map(Ok),
                    Ok(None) => Ok(Ok(None)),
                    Err(ReopenError::Storage(e)) => Err(e),
                    Err(bad @ ReopenError::BadRow(_)) => Ok(Err(bad.to_string())),
                });
                then(result.and_then(|r| r));
                false
            }
            Step::One(Write::Delete { job, place, then }) => {
                let store = Arc::clone(&self.store);
                self.until_done(|db| {
                    db.delete_job(job)?;
                    store.delete(place)
                });
                then(Ok(()));
                false
            }
            Step::One(Write::SequenceRunning { job }) => {
                self.until_done(|db| db.set_running_again(job));
                false
            }
        }
    }

    /// Runs `f` until it succeeds, every [`RETRY`].
    fn until_done<T>(&mut self, mut f: impl FnMut(&mut Db) -> anyhow::Result<T>) -> T {
        loop {
            match self.attempt(&mut f) {
                Ok(value) => return value,
                Err(_) => std::thread::sleep(RETRY),
            }
        }
    }

    /// Runs `f` once on the database (reopened if a failure closed it), timing it for
    /// the stall check and reporting storage available or not.
    fn attempt<T>(&mut self, f: impl FnOnce(&mut Db) -> anyhow::Result<T>) -> Result<T, String> {
        let since = self.status.started.elapsed().as_millis() as u64 + 1;
        self.status.busy_since.store(since, Ordering::SeqCst);
        let durability = self.durability;
        let f = |db: &mut Db| {
            db.set_durability(durability)?;
            f(db)
        };
        let result = match self.db.as_mut() {
            Some(db) => f(db),
            None => Db::open(&self.db_path, false).and_then(|db| f(self.db.insert(db))),
        };
        self.status.busy_since.store(0, Ordering::SeqCst);
        match result {
            Ok(value) => {
                self.status.report(self.hooks.as_ref(), Ok(()));
                Ok(value)
            }
            Err(e) => {
                let reason = one_line(&e);
                // A connection that failed may keep failing (an I/O error latches in
                // it): the next attempt opens a fresh one.
                self.db = None;
                self.status.report(self.hooks.as_ref(), Err(reason.clone()));
                Err(reason)
            }
        }
    }
}

/// An error and its causes on one line.
fn one_line(e: &anyhow::Error) -> String {
    format!("{e:#}").replace('\n', " ")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event() -> EventWrite {
        EventWrite {
            job: 1,
            event: JobEvent {
                seq: 1,
                unix_ms: 0,
                kind: "k".into(),
                detail: String::new(),
            },
        }
    }

    #[test]
    fn only_what_saves_work_is_committed_without_a_sync() {
        let job = |sequence| {
            Step::One(Write::InsertJob {
                job: Box::new(StoredJob {
                    sequence,
                    ..crate::db::tests::job(2, protocol::Sampling::Grid)
                }),
                then: Box::new(|_| {}),
            })
        };
        let ordered = [
            Step::Tiles(Vec::new(), vec![event()], Vec::new()),
            Step::One(Write::Event(event())),
            Step::One(Write::Started {
                job: 1,
                at_unix_ms: 0,
            }),
            job(Some(1)),
        ];
        for step in &ordered {
            assert_eq!(step.durability(), Durability::Ordered);
        }
        let announced = || Announcement::worker(0, "joined", serde_json::Map::new());
        let synced = [
            Step::Tiles(Vec::new(), vec![event()], vec![announced()]),
            Step::One(Write::Announce(announced())),
            job(None),
            Step::One(Write::ForgetTiles {
                job: 1,
                tiles: vec![0],
            }),
            Step::One(Write::SequenceRunning { job: 1 }),
            Step::One(Write::Delete {
                job: 1,
                place: ImagePlace::Job(1),
                then: Box::new(|_| {}),
            }),
            Step::Probe,
        ];
        for step in &synced {
            assert_eq!(step.durability(), Durability::Synced);
        }
    }
}
