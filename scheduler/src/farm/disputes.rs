//! Machines caught returning wrong pixels, and copies of a tile that disagree.
//!
//! The executor holds the pixels and the renderer: it compares two copies and, when
//! they differ, renders the pixels where they do to find which is wrong. What follows
//! is the core's: which machine is quarantined, what it rendered that is taken back,
//! and what a copy that settles nothing means.

use protocol::JobId;

use super::{Effect, Farm};
use crate::tiles::Event;
use crate::Millis;

/// What the executor found comparing a duplicate copy of a tile with the accepted
/// one.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CopyVerdict {
    /// The same pixels (or the same state, for a job in passes).
    Same,
    /// They differ: why the accepted copy is wrong and why the duplicate is, where the
    /// pixels rendered again showed it (`None`: not shown wrong, or nothing could be
    /// rendered to tell).
    Differs {
        accepted_wrong: Option<String>,
        copy_wrong: Option<String>,
    },
}

/// A straggler's copy of a tile whose result was accepted already.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Duplicate {
    pub job: JobId,
    pub tile: u32,
    /// The machine whose result was accepted, if known (the executor keeps it with
    /// the tile's pixels, also once the job is over).
    pub accepted_by: Option<String>,
    /// The machine that sent the copy.
    pub copy_by: String,
    pub verdict: CopyVerdict,
}

impl Farm {
    /// Shuts `machine` out: the executor hears first (to drop what it holds of it),
    /// then the tiles it rendered in the active jobs not in passes are taken back and
    /// its workers get no tile again.
    pub(super) fn quarantine(
        &mut self,
        now: Millis,
        machine: String,
        caught_in: JobId,
        reason: String,
        effects: &mut Vec<Effect>,
    ) {
        let passes = &self.passes;
        let tiles = &self.tiles;
        let taken = self.renderers.take_back(&machine, |job| {
            tiles.is_active(job) && !passes.contains_key(&job)
        });
        effects.push(Effect::Quarantined {
            machine: machine.clone(),
            caught_in,
            reason,
            taken: taken.clone(),
        });
        let mut revoke = Vec::new();
        for (job, tiles) in taken {
            revoke.extend(tiles.iter().map(|&t| (job, t)));
            effects.push(Effect::TakenBack { job, tiles });
        }
        self.tiles_event(now, Event::Quarantine { machine, revoke }, effects);
    }

    /// Settles a duplicate copy: each machine shown wrong is quarantined, the accepted
    /// copy's first (taking its tile back if its job is still active); a copy that
    /// shows nothing wrong changes nothing.
    pub(super) fn duplicate(&mut self, now: Millis, d: Duplicate, effects: &mut Vec<Effect>) {
        let Duplicate {
            job,
            tile,
            accepted_by,
            copy_by,
            verdict,
        } = d;
        let same = verdict == CopyVerdict::Same;
        let (accepted_wrong, copy_wrong) = match verdict {
            CopyVerdict::Same => (None, None),
            CopyVerdict::Differs {
                accepted_wrong,
                copy_wrong,
            } => (accepted_wrong, copy_wrong),
        };
        let mut settled = false;
        if let (Some(wrong), Some(first)) = (accepted_wrong, accepted_by) {
            let reason = format!(
                "returned wrong pixels for tile {tile} of job {job}: {wrong} (found comparing \
                 its result with {copy_by}'s copy)"
            );
            self.quarantine(now, first, job, reason, effects);
            settled = true;
        }
        if let Some(wrong) = copy_wrong {
            let reason = format!(
                "returned wrong pixels for tile {tile} of job {job}: {wrong} (found comparing \
                 its copy with the accepted result)"
            );
            self.quarantine(now, copy_by.clone(), job, reason, effects);
            settled = true;
        }
        if !settled {
            effects.push(Effect::DuplicateSettled {
                job,
                tile,
                machine: copy_by,
                same,
            });
        }
    }
}
