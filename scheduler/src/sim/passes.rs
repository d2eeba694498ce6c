//! Jobs rendered in passes (adaptive sampling), as the daemon runs them on the core:
//! the pass added up off the lock when the core asks, its totals fed back, and the
//! tiles' rungs kept as the core's pass actions say.
//!
//! The frame is a model: its estimated error halves every [`RUNGS_PER_HALVING`] rungs
//! from [`FIRST_ERROR`] levels, a tile's samples double every [`RUNGS_PER_DOUBLING`],
//! and taking a tile from one rung to the next costs the samples it adds. The job aims
//! for [`TARGET`] levels: one halving, which takes two passes.

use protocol::JobId;

use super::{Ev, Micros, Sim, SimJob, MS};
use crate::farm::{Input, PassAction, PassInput, PassTile};
use crate::passes::{Passes, RungCheck};

/// The frame's estimated error at rung 0, in levels.
pub(super) const FIRST_ERROR: f64 = 4.0;
/// The error the jobs in passes aim for.
pub(super) const TARGET: f64 = 2.0;
/// The ladder's last rung.
pub(super) const LAST_RUNG: u32 = 120;
pub(super) const RUNGS_PER_HALVING: f64 = 28.0;
pub(super) const RUNGS_PER_DOUBLING: f64 = 28.0;

/// What the daemon holds of a job in passes beside the core: each tile's rung.
pub(super) struct SimPasses {
    /// The rung of the pass under way.
    pub(super) rung: u32,
    /// The rung each tile has reached (`None` before its first answer).
    pub(super) reached: Vec<Option<u32>>,
}

impl SimPasses {
    pub(super) fn new(tiles: usize) -> SimPasses {
        SimPasses {
            rung: 0,
            reached: vec![None; tiles],
        }
    }

    /// The passes the core runs for such a job.
    pub(super) fn passes() -> Passes {
        Passes::new(TARGET, LAST_RUNG)
    }
}

/// A tile's samples at `rung`, as a multiple of its first rung's.
fn samples(rung: Option<u32>) -> f64 {
    rung.map_or(0.0, |k| (f64::from(k) / RUNGS_PER_DOUBLING).exp2())
}

impl SimJob {
    /// Reference-thread microseconds to render the tile now: all of it, or (a job in
    /// passes) the samples its pass adds.
    pub(super) fn cost(&self, tile: u32) -> Micros {
        let base = self.costs[tile as usize];
        match &self.passes {
            None => base,
            Some(p) => {
                let added = samples(Some(p.rung)) - samples(p.reached[tile as usize]);
                ((base as f64 * added.max(0.0)).round() as Micros).max(1)
            }
        }
    }
}

impl Sim<'_> {
    /// Carries out one of the core's actions about a job in passes, as the daemon does.
    pub(super) fn apply_pass(&mut self, action: PassAction) {
        match action {
            PassAction::AddUp { job, pass, rungs } => {
                // Adding a pass up reads every tile's state: about an image's encoding.
                let rungs = (*rungs.start(), *rungs.end());
                let at = self.now + self.image_encode;
                self.agenda.push(at, Ev::PassAddedUp { job, pass, rungs });
            }
            PassAction::Continued { .. } => self.out.passes_continued += 1,
            PassAction::Start {
                job, rung, send, ..
            } => {
                let slot = self.slot(job);
                let j = &mut self.jobs[slot];
                let Some(p) = j.passes.as_mut() else {
                    self.out.model_mismatches += 1;
                    return;
                };
                p.rung = rung;
                let mut next = send.iter().peekable();
                for t in 0..p.reached.len() {
                    if next.next_if_eq(&&(t as u32)).is_some() {
                        j.accepted[t] = 0;
                    } else {
                        p.reached[t] = Some(rung);
                    }
                }
            }
            PassAction::Finished { job, .. } => self.tiles_ended(job, true),
            // The simulated workers are honest: nothing is taken back.
            PassAction::TakenBack { .. } | PassAction::TooLate { .. } => {
                self.out.model_mismatches += 1
            }
        }
    }

    /// A pass's totals, from the model: fed to the core.
    pub(super) fn pass_added_up(&mut self, job: JobId, pass: u32, (first, last): (u32, u32)) {
        let j = &self.jobs[self.slot(job)];
        let Some(p) = &j.passes else {
            self.out.model_mismatches += 1;
            return;
        };
        let checks = (first..=last)
            .map(|rung| {
                let estimate = FIRST_ERROR * (-f64::from(rung) / RUNGS_PER_HALVING).exp2();
                RungCheck {
                    rung,
                    estimate,
                    meets: estimate <= TARGET || rung >= LAST_RUNG,
                }
            })
            .collect();
        let tiles = p
            .reached
            .iter()
            .map(|&rung| PassTile {
                rung,
                next_work: match rung {
                    Some(k) if k >= LAST_RUNG => None,
                    Some(k) => Some(k + 1),
                    None => Some(0),
                },
            })
            .collect::<Vec<_>>();
        let frame_samples = samples(Some(p.rung)) * tiles.len() as f64;
        let input = PassInput::Evaluated {
            job,
            pass,
            checks,
            tiles,
            elapsed_ms: self.now.saturating_sub(j.sent) / MS,
            samples: frame_samples.round() as u64,
        };
        self.feed(Input::Pass(input));
    }
}
