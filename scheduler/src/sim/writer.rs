//! The persistence thread: one writer carrying out the writes in order, batching
//! consecutive tiles, failing on a disk that is down and trying again, and reporting
//! storage unavailable and available as the daemon does. It is the one part of the
//! daemon with a queue and a pace of its own, so it reads apart from the coordinator.

use std::collections::VecDeque;

use protocol::JobId;

use super::{Ev, Micros, Sim, MS};
use crate::farm::Input;
use crate::lifecycle;

/// Why a write failed, as the simulated daemon reports it.
const STORAGE_DOWN: &str = "the simulated disk takes no writes";

/// Tiles written in one transaction at most (the daemon's batch).
const TILE_BATCH: u32 = 256;

/// One write queued on the persistence thread.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Write {
    /// A new job's row (its client waits for the answer).
    Insert(JobId),
    /// Accepted tiles (consecutive ones are one entry, written in batches).
    Tiles(u32),
    /// A job's first tile went out.
    Started(JobId),
    Image(JobId),
    End(JobId),
    Delete(JobId),
    /// Not queued: after a failed insert, checks that the disk can be written again.
    Probe,
}

#[derive(Default)]
pub(super) struct Writer {
    queue: VecDeque<Write>,
    /// The write being carried out (attempted, or waiting to be tried again).
    current: Option<Write>,
    /// The disk is probed before any other write.
    probing: bool,
    /// Storage is reported unavailable, since `down_since`.
    pub(super) down: bool,
    pub(super) down_since: Micros,
    /// The disk's outage count when the attempt in progress began, and whether the disk
    /// was down then (the attempt fails at once).
    attempt_epoch: u64,
    attempt_doomed: bool,
}

impl Sim<'_> {
    /// Queues a write; the writer takes it up at once if it is idle.
    pub(super) fn persist(&mut self, write: Write) {
        match (write, self.writer.queue.back_mut()) {
            (Write::Tiles(n), Some(Write::Tiles(queued))) => *queued += n,
            _ => self.writer.queue.push_back(write),
        }
        self.next_write();
    }

    /// The writer, if idle, takes the next write (the probe first, after a failed
    /// insert; consecutive tiles in one batch) and attempts it.
    fn next_write(&mut self) {
        if self.writer.current.is_some() {
            return;
        }
        let write = if self.writer.probing {
            Write::Probe
        } else {
            match self.writer.queue.pop_front() {
                None => return,
                Some(Write::Tiles(n)) if n > TILE_BATCH => {
                    self.writer.queue.push_front(Write::Tiles(n - TILE_BATCH));
                    Write::Tiles(TILE_BATCH)
                }
                Some(write) => write,
            }
        };
        self.writer.current = Some(write);
        self.attempt_write();
    }

    /// One attempt of the current write: it fails at once on a disk that is down, and
    /// otherwise ends after its write time (failed if the disk went down meanwhile).
    pub(super) fn attempt_write(&mut self) {
        let Some(write) = self.writer.current else {
            return;
        };
        self.writer.attempt_epoch = self.disk_epoch;
        self.writer.attempt_doomed = self.disk_down;
        let took = match write {
            Write::Image(_) => self.image_write,
            _ => self.row_write,
        };
        let at = if self.disk_down {
            self.now
        } else {
            self.now + took
        };
        self.agenda.push(at, Ev::WriteDone);
    }

    /// The attempt in progress ends: storage is reported available or not (on a
    /// change), and the write's outcome goes where the daemon's callbacks send it.
    pub(super) fn write_done(&mut self) {
        let Some(write) = self.writer.current.take() else {
            return;
        };
        let ok = !self.writer.attempt_doomed && self.writer.attempt_epoch == self.disk_epoch;
        if !ok {
            self.out.write_failures += 1;
            self.storage_status(false);
            if let Write::Insert(job) = write {
                // Its client is waiting: it is answered at once, and the disk is probed
                // before anything else is written.
                self.writer.probing = true;
                self.life(lifecycle::Event::StoreFailed {
                    job,
                    message: STORAGE_DOWN.into(),
                });
                self.next_write();
            } else {
                self.writer.current = Some(write);
                self.agenda
                    .push(self.now + self.cfg.limits.retry_ms * MS, Ev::WriteRetry);
            }
            return;
        }
        self.out.writes += 1;
        self.storage_status(true);
        match write {
            Write::Probe => self.writer.probing = false,
            Write::Insert(job) => self.life(lifecycle::Event::Stored { job }),
            Write::Tiles(n) => self.out.tiles_written += u64::from(n),
            Write::Started(_) => {}
            Write::Image(job) => {
                self.out.images_stored += 1;
                self.life(lifecycle::Event::ImageStored {
                    job,
                    result: Ok(()),
                });
            }
            Write::End(job) => self.end_recorded(job),
            Write::Delete(job) => {
                self.out.jobs_deleted += 1;
                self.life(lifecycle::Event::Deleted { job });
            }
        }
        self.next_write();
    }

    /// Storage became unavailable or available again: both machines hear it, in the
    /// daemon's order (the tile scheduler stops first and resumes last).
    fn storage_status(&mut self, available: bool) {
        if self.writer.down != available {
            return;
        }
        self.writer.down = !available;
        if available {
            self.out.storage_unavailable_ms +=
                (self.now - self.writer.down_since) as f64 / MS as f64;
            self.feed(Input::Storage(Ok(())));
        } else {
            self.writer.down_since = self.now;
            self.out.storage_unavailable += 1;
            self.feed(Input::Storage(Err(STORAGE_DOWN.into())));
        }
    }

    /// The disk's next outage (Poisson), while it works.
    pub(super) fn arm_storage_outage(&mut self) {
        if self.cfg.storage_outages_per_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let after = self
                .storage_rng
                .exponential(hour / self.cfg.storage_outages_per_hour);
            self.agenda
                .push(self.now + after.round() as Micros, Ev::StorageOutage);
        }
    }
}
