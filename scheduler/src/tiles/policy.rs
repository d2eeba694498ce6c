//! The knobs of the tile scheduler's policy and their defaults: plain settings, read
//! by every part of the scheduler and written by none, so they stand apart from the
//! state they govern.

use super::Millis;

/// The knobs of the policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Policy {
    /// A worker silent for this long is dropped.
    pub heartbeat_timeout: Millis,
    /// The lease of a job's tiles before any of them has been measured.
    pub initial_lease: Millis,
    /// No lease is shorter than this, however fast the tiles.
    pub min_lease: Millis,
    /// A lease lasts this many times the job's slowest measured tile (and at least
    /// four times its mean).
    pub lease_factor: u64,
    /// Failures of one tile reported by workers before its job fails.
    pub max_attempts: u32,
    /// Failures of one job's tiles reported by one machine before the machine is
    /// blocked from the job.
    pub block_after: u32,
    /// Whether to duplicate stragglers near the end of a job.
    pub speculate: bool,
    /// Times one tile may be lost with its worker (connection closed, or dropped for
    /// silence, while holding it) before its job fails: a tile that crashes whoever
    /// renders it, or a farm whose workers keep losing their connection.
    pub max_losses: u32,
    /// How long a job with tiles waiting may go with workers connected but none that
    /// may take any of them before it fails.
    pub stall_timeout: Millis,
    /// The most tiles a worker may hold per thread, however long its round trip.
    pub max_credit_per_thread: u32,
    /// A gap between two calls longer than this is a pause of the coordinator itself,
    /// and counts only as one `wake_interval` (see the [module doc](super)).
    pub pause_threshold: Millis,
    /// The longest the daemon may wait between two calls while a worker is connected.
    pub wake_interval: Millis,
    /// The least time a worker holding a tile whose lease ran out may go without
    /// returning any result before it is marked unresponsive (see the
    /// [module doc](super)).
    pub progress_timeout: Millis,
    /// ... or this many times its pace (its slowest time per result, or the slowest
    /// measured tile of the jobs it holds), when that is longer.
    pub progress_factor: u64,
    /// The most tiles one call hands out. A call that could hand out more (a job of
    /// thousands of tiles submitted to a farm of thousands of idle threads) stops
    /// there and asks to be called again at once ([`Scheduler::has_more`]): the
    /// daemon holds its lock for a bounded time, and what arrived meanwhile is heard
    /// between two calls. The tiles go out in the same order either way.
    ///
    /// [`Scheduler::has_more`]: super::Scheduler::has_more
    pub handout_per_call: usize,
    /// The most checks one call makes: leases run out, entries of silent workers
    /// looked at, workers looked at for progress, and scenes forgotten by a worker.
    /// When more are due (thousands of leases running out together on a large farm,
    /// the end of a job whose scene thousands of workers have), the call stops there
    /// and asks to be called again at once, as for the hand-out: what is due is
    /// checked over several calls, at the same time.
    pub checks_per_call: usize,
}

impl Default for Policy {
    fn default() -> Self {
        Policy {
            heartbeat_timeout: 5_000,
            initial_lease: 60_000,
            min_lease: 1_000,
            lease_factor: 3,
            max_attempts: 5,
            block_after: 2,
            speculate: true,
            max_losses: 8,
            stall_timeout: 30_000,
            max_credit_per_thread: 256,
            pause_threshold: 2_000,
            wake_interval: 1_000,
            progress_timeout: 20_000,
            progress_factor: 16,
            handout_per_call: 256,
            checks_per_call: 512,
        }
    }
}

impl Policy {
    /// The wake interval in effect: at least 1 ms, and no more than the pause threshold,
    /// so that a daemon keeping to [`Scheduler::next_deadline`] never looks paused.
    ///
    /// [`Scheduler::next_deadline`]: super::Scheduler::next_deadline
    pub(super) fn wake(&self) -> Millis {
        self.wake_interval.clamp(1, self.pause_threshold.max(1))
    }
}
