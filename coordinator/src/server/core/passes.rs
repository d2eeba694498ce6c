//! An adaptive job's passes, as the executor of the core's decisions: a pass's tiles
//! added up off the lock when the core says the pass is complete, the totals fed back,
//! and the tiles' states kept as the core's pass actions say.

use std::sync::Arc;

use protocol::JobId;
use scheduler::farm::{Input, PassAction, PassInput};
use tracing::{error, info, warn};

use super::{Core, Shared};
use crate::server::adaptive::{self, AdaptiveTile, Evaluation, PassSnapshot};

impl Core {
    /// Carries out one of the core's actions about a job in passes.
    pub(super) fn apply_pass(&mut self, sh: &Arc<Shared>, action: PassAction) {
        match action {
            PassAction::AddUp { job, pass, rungs } => self.add_up(sh, job, pass, rungs),
            PassAction::Finished {
                job,
                pass,
                rung,
                out_of_time,
            } => {
                let Some(estimate) = self.take_evaluation(job, true) else {
                    return;
                };
                let Some(record) = self.jobs.get_mut(&job) else {
                    return;
                };
                record.stopped_on_time_limit |= out_of_time;
                record.tiles_recorded = record.tiles_total;
                let why = if out_of_time {
                    "the time limit is reached"
                } else {
                    "the target is met"
                };
                info!(
                    job,
                    passes = pass + 1,
                    rung,
                    estimate,
                    "adaptive job: {why}"
                );
                let detail = format!(
                    "pass {} at rung {rung}: estimated error {estimate:.3} levels; {why}",
                    pass + 1
                );
                self.log(sh, job, "adaptive_pass", detail);
            }
            PassAction::Continued { job, pass, rung } => {
                let Some(estimate) = self.take_evaluation(job, false) else {
                    return;
                };
                info!(job, pass, rung, estimate, "adaptive job: next pass");
                let detail = format!(
                    "estimated error {estimate:.3} levels: pass {pass} goes on to rung {rung}"
                );
                self.log(sh, job, "adaptive_pass", detail);
            }
            PassAction::TakenBack { job, taken, .. } => {
                warn!(
                    job,
                    tiles = taken.len(),
                    "rendering again the adaptive tiles a quarantined machine built"
                );
                self.held.retain(|(j, _), _| *j != job);
                if let Some(ad) = self.jobs.get_mut(&job).and_then(|r| r.adaptive.as_mut()) {
                    for t in taken {
                        if let Some(tile) = ad.tiles.get_mut(t as usize) {
                            *tile = AdaptiveTile::unrendered();
                        }
                    }
                }
            }
            PassAction::TooLate { job, taken } => error!(
                job,
                tiles = taken.len(),
                "a finished adaptive job holds tiles of a quarantined machine: submit it again"
            ),
            PassAction::Start {
                job, rung, send, ..
            } => {
                let Some(ad) = self.jobs.get_mut(&job).and_then(|r| r.adaptive.as_mut()) else {
                    return;
                };
                for (i, t) in ad.tiles.iter_mut().enumerate() {
                    if send.binary_search(&(i as u32)).is_ok() {
                        t.previous = t.state.clone();
                    } else {
                        t.rung = Some(rung);
                    }
                }
            }
        }
    }

    /// Every tile of an adaptive job's pass is in: its totals are added up off the
    /// lock, and fed back to the core ([`Core::pass_evaluated`]).
    fn add_up(
        &mut self,
        sh: &Arc<Shared>,
        job: JobId,
        pass: u32,
        rungs: std::ops::RangeInclusive<u32>,
    ) {
        let Some(record) = self.jobs.get(&job) else {
            return;
        };
        let (Some(ad), Some(scene)) = (record.adaptive.as_ref(), record.scene.clone()) else {
            return;
        };
        let snap = PassSnapshot {
            rungs,
            settings: record.settings,
            rects: record.tiles.clone(),
            states: ad.tiles.iter().map(|t| t.state.clone()).collect(),
            paint_last: record.time_limit_ms.is_some(),
        };
        let (hash, frame) = (record.hash, record.frame);
        let assets = Arc::clone(&record.assets);
        let shared = Arc::clone(sh);
        sh.runtime.spawn_blocking(move || {
            let verifier = &shared.verifier;
            let files = || shared.mesh_files(&assets);
            let evaluation = verifier
                .tracer(hash, frame, snap.settings, &scene, files)
                .and_then(|tracer| adaptive::evaluate(verifier, &tracer, snap));
            shared.lock().pass_evaluated(&shared, job, pass, evaluation);
        });
    }

    /// A pass's totals are in: kept aside for the core's verdict (which may find them
    /// too late, for a pass restarted or a job ended meanwhile), and fed to the core
    /// with the tiles as they stand and how long the job has rendered.
    fn pass_evaluated(
        &mut self,
        sh: &Arc<Shared>,
        job: JobId,
        pass: u32,
        evaluation: Result<Evaluation, String>,
    ) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(ad) = record.adaptive.as_mut() else {
            return;
        };
        let input = match evaluation {
            Err(message) => {
                error!(job, pass, error = %message, "cannot add up an adaptive pass");
                PassInput::Failed { job, pass, message }
            }
            Ok(evaluation) => {
                // Rendering time, less the coordinator's own downtime: what a limit
                // budgets.
                let now = self.now.unix_ms;
                let elapsed_ms = record.rendered_before_ms
                    + now.saturating_sub(record.running_since.unwrap_or(now));
                let input = PassInput::Evaluated {
                    job,
                    pass,
                    checks: evaluation.checks.clone(),
                    tiles: ad.pass_tiles(),
                    elapsed_ms,
                    samples: evaluation.totals.samples,
                };
                ad.evaluation = Some(evaluation);
                input
            }
        };
        self.feed(sh, Input::Pass(input));
        // Totals the core did not rule on (a pass restarted, a job ended meanwhile)
        // are not kept.
        if let Some(ad) = self.jobs.get_mut(&job).and_then(|r| r.adaptive.as_mut()) {
            ad.evaluation = None;
        }
        sh.changed();
    }

    /// The totals of the pass the core has ruled on: they become the job's, with its
    /// image if the pass ended it (`last`). Returns the estimate, or `None` when there
    /// are none (the core rules only on totals fed to it).
    fn take_evaluation(&mut self, job: JobId, last: bool) -> Option<f64> {
        let record = self.jobs.get_mut(&job)?;
        let evaluation = record.adaptive.as_mut()?.evaluation.take()?;
        let t = evaluation.totals;
        let pixels = u64::from(record.settings.width) * u64::from(record.settings.height);
        record.totals.samples = t.samples;
        let estimate = t.estimated_error();
        if estimate.is_finite() {
            record.totals.error_sq_sum = estimate * estimate * pixels as f64;
            record.totals.error_pixels = pixels;
        }
        if last {
            record.image = evaluation.image;
        }
        Some(estimate)
    }

    /// A machine of the quarantine built some of an adaptive job's tiles: the core
    /// takes them back to nothing and starts the pass under way again under a new
    /// number (at the same rung), so that no answer built on their states counts and
    /// every rung is added up again; or says it is too late.
    pub(super) fn take_back_adaptive(&mut self, sh: &Arc<Shared>, job: JobId, machine: &str) {
        let Some(ad) = self.jobs.get(&job).and_then(|r| r.adaptive.as_ref()) else {
            return;
        };
        let taken: Vec<u32> = (0..ad.tiles.len() as u32)
            .filter(|&t| {
                ad.tiles[t as usize]
                    .machines
                    .iter()
                    .any(|m| &**m == machine)
            })
            .collect();
        if taken.is_empty() {
            return;
        }
        let tiles = ad.pass_tiles();
        self.feed(sh, Input::Pass(PassInput::TakeBack { job, taken, tiles }));
    }
}
