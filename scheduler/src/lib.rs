//! Tessera's decisions, as pure state machines.
//!
//! Nothing here owns a socket, a file, a clock or a thread: the coordinator daemon
//! feeds events (with the time on each) and carries out the actions returned, and the
//! tests and the simulator feed scripted or random events with a virtual clock. The
//! crate depends on nothing but the protocol's ids, so the compiler keeps I/O out.
//!
//! - [`tiles`]: which tile goes to which worker, leases, heartbeats, stragglers,
//!   retries and blocks.
//! - [`lifecycle`]: the jobs themselves: admission, Queued → Running → Done, Failed or
//!   Cancelled, when each change is stored, and when a failure is final.
//! - [`passes`]: how far each pass of an adaptive job goes, and which rung is its image.
//! - [`sequence`]: which frames of a sequence job start when, and its state.
//! - [`sim`]: a farm of simulated workers driving both, to show the design holds far
//!   beyond one machine.

pub mod farm;
pub mod lifecycle;
pub mod passes;
pub mod sequence;
pub mod sim;
pub mod tiles;

pub use tiles::{Action, Counters, Event, Millis, Policy, Scheduler};

/// Timer slack: a daemon (and the simulator) puts a wake-up for a deadline off to the
/// next multiple of this, so that the deadlines of many leases and workers falling
/// close together cost one wake-up, not one each. Late by at most this, a `Timeout`
/// decides the same; it is far below the pause threshold.
pub const TIMER_SLACK: Millis = 100;

/// The time at which to wake for `deadline`, with [`TIMER_SLACK`].
pub fn wake_time(deadline: Millis) -> Millis {
    deadline.div_ceil(TIMER_SLACK) * TIMER_SLACK
}
