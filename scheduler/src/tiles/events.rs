//! The tile scheduler's inputs and outputs: the [`Event`]s the daemon feeds it and
//! the [`Action`]s it returns. They are the whole of its contract with the daemon
//! (and with the tests and the simulator), read apart from how the scheduler decides.

use protocol::{JobId, SceneHash, WorkerId};

use super::Millis;

/// Something that happened, as the daemon saw it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// The deadline of [`Scheduler::next_deadline`] came (or the daemon looks anyway):
    /// silent workers are dropped, leases run out, stalled jobs fail.
    ///
    /// [`Scheduler::next_deadline`]: super::Scheduler::next_deadline
    Timeout,
    /// A worker connected. `machine` is the name it gave, if any: reported failures and
    /// blocks are counted per machine, so that a worker that fails a job's tiles and
    /// comes back under the same name (a restarted service) is still kept from them.
    /// A worker without one is a machine of its own.
    WorkerJoined {
        worker: WorkerId,
        threads: u32,
        machine: Option<String>,
    },
    /// The worker is alive (any message from it counts as much).
    Heartbeat {
        worker: WorkerId,
    },
    /// The worker's connection is gone; its tiles go back to their queues. Nothing
    /// counts against its machine: a lost connection proves nothing about it. Each
    /// tile it held counts one loss towards [`Policy::max_losses`].
    ///
    /// [`Policy::max_losses`]: super::Policy::max_losses
    WorkerLeft {
        worker: WorkerId,
    },
    /// The worker is shutting down: it finishes what it holds and gets nothing more.
    WorkerDraining {
        worker: WorkerId,
    },
    JobSubmitted {
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
    },
    /// A result from the worker that counts: either alone, or, on a tile whose result
    /// from another machine is held, as its confirmation (the daemon found the two
    /// identical).
    TileDone {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// A result that counts only once another machine returns the same bytes: it is
    /// held, and the tile goes to another machine. `required` confirmations wait for
    /// a machine; optional ones (audits) are given up when none may give them.
    TileToConfirm {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        required: bool,
    },
    /// The machine returned wrong pixels: it gets no tile again, its tiles and held
    /// results go back to the queue, and so do the done tiles of `revoke` (those the
    /// daemon accepted from it in active jobs).
    Quarantine {
        machine: String,
        revoke: Vec<(JobId, u32)>,
    },
    /// The daemon measured the worker's round trip and its time per tile (on one
    /// thread): its credit follows.
    WorkerPace {
        worker: WorkerId,
        rtt: Millis,
        tile: Millis,
    },
    /// The worker could not render the tile.
    TileFailed {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        message: String,
    },
    CancelJob {
        job: JobId,
    },
    /// An operator paused the job: none of its tiles is handed out (copies included)
    /// until `ResumeJob`. Tiles already out may finish and count. A paused job never
    /// stalls: waiting is what it was asked to do. The pause holds for a job not yet
    /// submitted or resumed (the daemon restores a paused job this way).
    PauseJob {
        job: JobId,
    },
    /// The job renders for an interactive view (docs/studio.md): its tiles go ahead of
    /// every batch job's, whatever their priorities, but while batch tiles wait at
    /// least one tile in every [`INTERACTIVE_RUN`] + 1 handed out is a batch tile, so
    /// that batch jobs are slowed, never starved. Holds for the job's life (a daemon
    /// that renders a job in several runs marks each run).
    ///
    /// [`INTERACTIVE_RUN`]: super::INTERACTIVE_RUN
    Interactive {
        job: JobId,
    },
    /// The paused job's tiles are handed out again.
    ResumeJob {
        job: JobId,
    },
    /// The job's priority changed: the next free slots follow the new order.
    SetPriority {
        job: JobId,
        priority: i32,
    },
    /// Storage cannot record results: hand out no new tile (results of tiles already
    /// out are still accepted) until `StorageAvailable`.
    StorageUnavailable,
    /// Storage records results again: every worker is filled.
    StorageAvailable,
    /// An operator disabled the machine: its workers get no new tile (tiles they hold
    /// may finish and count) until `EnableMachine`. Kept by machine name, so that it
    /// holds for workers of that machine that connect later.
    DisableMachine {
        machine: String,
    },
    /// The disabled machine's workers take tiles again.
    EnableMachine {
        machine: String,
    },
    /// An operator has the job's tiles rendered again, wherever they are: waiting
    /// (nothing changes), out on workers (their results will count for nothing; their
    /// slots are free at once), held for confirmation (dropped), or done (taken back).
    /// Tile numbers past the job's are ignored (the daemon refuses them first).
    RequeueTiles {
        job: JobId,
        tiles: Vec<u32>,
    },
    /// The last call stopped at the hand-out bound ([`Scheduler::has_more`]): hand out
    /// the next share of what is left, and nothing else.
    ///
    /// [`Scheduler::has_more`]: super::Scheduler::has_more
    Continue,
    /// The job's tiles (confirmations included) go only to workers that have every
    /// one of `tags`; none: to any worker. Held by id like a pause: told before
    /// `JobSubmitted` (or a resumed job), it holds from its first tile, and across the
    /// runs of a job rendered in several, until told again.
    RequireTags {
        job: JobId,
        tags: Vec<String>,
    },
    /// The worker's tags: told just before its `WorkerJoined`, so that its first tiles
    /// already follow them. Told again for a connected worker, the tiles it holds of
    /// jobs it no longer qualifies for go back to the queue.
    WorkerTags {
        worker: WorkerId,
        tags: Vec<String>,
    },
}

/// What the daemon must do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Action {
    /// Send the job's scene to the worker (before the `Assign` that follows).
    SendScene {
        worker: WorkerId,
        job: JobId,
    },
    /// Send the tile to the worker.
    Assign {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// Keep this result: it is the first for the tile.
    AcceptTile {
        job: JobId,
        tile: u32,
    },
    /// A second result for a tile already accepted: it must equal the first.
    DuplicateResult {
        job: JobId,
        tile: u32,
    },
    /// Keep this result aside: it counts once another machine's result equals it.
    HoldResult {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// No connected machine may confirm the held result: accept it as it is.
    AcceptHeld {
        job: JobId,
        tile: u32,
    },
    /// Tell the worker to drop the job's tiles it still holds.
    CancelOnWorker {
        worker: WorkerId,
        job: JobId,
    },
    /// The worker may drop the scene from its cache: no active job uses it.
    ForgetScene {
        worker: WorkerId,
        scene: SceneHash,
    },
    /// The worker missed its heartbeats: close its connection.
    DropWorker {
        worker: WorkerId,
    },
    /// The worker holds tiles whose leases ran out and has returned nothing for
    /// `silent` ms: it is marked unresponsive (it stays connected; its tiles are
    /// rendered elsewhere).
    WorkerUnresponsive {
        worker: WorkerId,
        silent: Millis,
    },
    /// An unresponsive worker returned a result: it takes tiles again.
    WorkerResponsive {
        worker: WorkerId,
    },
    /// Every tile is done: assemble and store the image.
    JobDone {
        job: JobId,
    },
    JobFailed {
        job: JobId,
        message: String,
    },
}
