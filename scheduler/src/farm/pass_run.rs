//! The core's part in jobs rendered in passes (adaptive sampling): when a pass is
//! complete, whether its totals end the job or start the next pass, which tiles that
//! pass sends, and a pass restarted when results it built on are taken back.
//!
//! [`Passes`] decides where each pass aims; this holds one per job and joins it to the
//! tile scheduler and the lifecycle. The executor keeps the bytes (each tile's state,
//! the frame) and does the arithmetic that needs the renderer (a pass's totals, off
//! the lock); it passes in what it measured, with the tiles' rungs and next work, and
//! gets told what to do with its bytes.

use std::ops::RangeInclusive;

use protocol::JobId;

use crate::passes::{Decision, Passes, RungCheck};

/// One tile of a job in passes, as the executor holds it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PassTile {
    /// The rung its state has reached (`None` without a state).
    pub rung: Option<u32>,
    /// The first rung after `rung` at which a block of the tile doubles (`Some(0)`
    /// without a state, `None` once every block is at its cap).
    pub next_work: Option<u32>,
}

/// Something the executor tells the core about a job in passes.
#[derive(Clone, Debug, PartialEq)]
pub enum PassInput {
    /// The totals of `pass`, added up after [`PassAction::AddUp`]: the verdicts at
    /// its rungs, the tiles as they stand, how long the job has rendered (less the
    /// coordinator's own downtime) and the frame's samples at the pass's rung.
    Evaluated {
        job: JobId,
        pass: u32,
        checks: Vec<RungCheck>,
        tiles: Vec<PassTile>,
        elapsed_ms: u64,
        samples: u64,
    },
    /// The totals of `pass` could not be added up: the job fails.
    Failed {
        job: JobId,
        pass: u32,
        message: String,
    },
    /// A machine caught returning wrong pixels built the states of `taken`: they go
    /// back to nothing and the pass under way starts again. `tiles` are the job's
    /// tiles as they stand, before the taking back.
    TakeBack {
        job: JobId,
        taken: Vec<u32>,
        tiles: Vec<PassTile>,
    },
}

/// Something the executor does with a job in passes' bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PassAction {
    /// Every tile of `pass` is in: add up the totals at `rungs` and feed
    /// [`PassInput::Evaluated`] (or [`PassInput::Failed`]).
    AddUp {
        job: JobId,
        pass: u32,
        rungs: RangeInclusive<u32>,
    },
    /// `pass` ends the job: its image is every tile at `rung`, the first to meet the
    /// target, or (`out_of_time`) the deepest rendered when the time limit is reached.
    /// The image is due next.
    Finished {
        job: JobId,
        pass: u32,
        rung: u32,
        out_of_time: bool,
    },
    /// The totals did not meet the target: `pass` goes on to `rung`.
    Continued { job: JobId, pass: u32, rung: u32 },
    /// `taken` go back to nothing (no state, no machines); `pass` is the pass under
    /// way's new number.
    TakenBack {
        job: JobId,
        pass: u32,
        taken: Vec<u32>,
    },
    /// Too late to take back `taken`: the job is past its passes.
    TooLate { job: JobId, taken: Vec<u32> },
    /// `pass` starts: the tiles of `send` go out from their states (which every
    /// answer of the pass is checked against); every other tile has reached `rung`.
    /// The job's tiles go out next.
    Start {
        job: JobId,
        pass: u32,
        rung: u32,
        send: Vec<u32>,
    },
}

/// A job in passes, as the core holds it.
#[derive(Clone, Debug)]
pub struct PassRun {
    passes: Passes,
    /// The pass is complete and its totals are being added up.
    evaluating: bool,
    /// An operator's pause: the scheduler forgets it when a run of the job ends, and
    /// each pass is one, so the next pass starts paused.
    paused: bool,
}

impl PassRun {
    pub fn new(passes: Passes) -> PassRun {
        PassRun {
            passes,
            evaluating: false,
            paused: false,
        }
    }

    /// The pass under way.
    pub fn pass(&self) -> u32 {
        self.passes.pass()
    }

    /// The rung the pass under way takes the tiles to.
    pub fn rung(&self) -> u32 {
        self.passes.rung()
    }

    /// Whether the pass is complete and its totals are being added up: no answer
    /// counts for it any more.
    pub fn evaluating(&self) -> bool {
        self.evaluating
    }

    /// Whether an answer for (`pass`, `rung`) counts: the pass is the one under way
    /// and still takes answers.
    pub fn takes(&self, pass: u32, rung: u32) -> bool {
        !self.evaluating && self.pass() == pass && self.rung() == rung
    }

    pub(super) fn set_paused(&mut self, paused: bool) {
        self.paused = paused;
    }

    pub(super) fn paused(&self) -> bool {
        self.paused
    }

    /// Every tile of the pass is in.
    pub(super) fn complete(&mut self, job: JobId) -> PassAction {
        self.evaluating = true;
        PassAction::AddUp {
            job,
            pass: self.pass(),
            rungs: self.passes.to_check(),
        }
    }

    /// Whether the answer to `pass` is awaited.
    pub(super) fn awaits(&self, pass: u32) -> bool {
        self.evaluating && self.pass() == pass
    }

    /// The totals of the pass: what [`Passes`] decides of them.
    pub(super) fn evaluated(
        &mut self,
        checks: &[RungCheck],
        tiles: &[PassTile],
        elapsed_ms: u64,
        samples: u64,
    ) -> Decision {
        self.evaluating = false;
        let first_work = tiles.iter().filter_map(|t| t.next_work).min();
        self.passes
            .pass_done_at(checks, first_work, elapsed_ms, samples)
    }

    pub(super) fn failed(&mut self) {
        self.evaluating = false;
    }

    /// Results the pass depends on were taken back: it starts again under a new
    /// number, at the same rung.
    pub(super) fn restart(&mut self) -> u32 {
        self.evaluating = false;
        self.passes.restart_pass()
    }

    /// The pass under way's start, from the tiles as they stand: every tile with work
    /// at its rung goes out; the others have reached the rung already. Returns the
    /// action and the tiles that count as done.
    pub(super) fn start(&self, job: JobId, tiles: &[PassTile]) -> (PassAction, Vec<u32>) {
        let rung = self.rung();
        let next_work: Vec<Option<u32>> = tiles
            .iter()
            .map(|t| {
                if t.rung == Some(rung) {
                    None
                } else {
                    t.next_work
                }
            })
            .collect();
        let send = crate::passes::tiles_with_work(&next_work, rung);
        let done: Vec<u32> = (0..tiles.len() as u32)
            .filter(|t| send.binary_search(t).is_err())
            .collect();
        let start = PassAction::Start {
            job,
            pass: self.pass(),
            rung,
            send,
        };
        (start, done)
    }
}
