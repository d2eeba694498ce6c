//! An adaptive job's passes: each pass's tiles added up off the lock once they are
//! all in, and then the job's image found or the next pass started.

use std::sync::Arc;

use protocol::JobId;
use scheduler::lifecycle::{self, Phase};
use scheduler::Event;
use tracing::{error, info};

use super::{unix_ms, Core, Shared};
use crate::server::adaptive::{self, Evaluation, PassSnapshot};

impl Core {
    /// Every tile of an adaptive job's pass is in: its totals are added up off the
    /// lock, and [`Core::pass_evaluated`] decides.
    pub(super) fn end_of_pass(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let (Some(ad), Some(scene)) = (record.adaptive.as_mut(), record.scene.clone()) else {
            return;
        };
        ad.evaluating = true;
        let snap = PassSnapshot {
            pass: ad.passes.pass(),
            rungs: ad.passes.to_check(),
            settings: record.settings,
            rects: record.tiles.clone(),
            states: ad.tiles.iter().map(|t| t.state.clone()).collect(),
            paint_last: record.time_limit_ms.is_some(),
        };
        let (hash, frame) = (record.hash, record.frame);
        let shared = Arc::clone(sh);
        sh.runtime.spawn_blocking(move || {
            let verifier = &shared.verifier;
            let evaluation = verifier
                .tracer(hash, frame, snap.settings, &scene)
                .and_then(|tracer| adaptive::evaluate(verifier, &tracer, snap));
            shared.lock().pass_evaluated(&shared, job, evaluation);
        });
    }

    /// A pass's totals are in: the job's image is found (the first rung that meets the
    /// target), or the next pass starts. A result for a pass that is no longer the
    /// job's (restarted, cancelled) counts for nothing.
    fn pass_evaluated(
        &mut self,
        sh: &Arc<Shared>,
        job: JobId,
        evaluation: Result<Evaluation, String>,
    ) {
        let running = self
            .farm
            .lifecycle()
            .job(job)
            .is_some_and(|j| matches!(j.phase, Phase::Queued | Phase::Running));
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(ad) = record.adaptive.as_mut() else {
            return;
        };
        let evaluation = match evaluation {
            Ok(e) if e.pass != ad.passes.pass() || !ad.evaluating => return,
            Ok(e) => e,
            Err(message) => {
                ad.evaluating = false;
                if !running {
                    return;
                }
                let message = format!("cannot add up the pass's tiles: {message}");
                error!(job, error = %message, "adaptive job failed");
                self.life_event(sh, lifecycle::Event::TilesFailed { job, message });
                return;
            }
        };
        ad.evaluating = false;
        if !running {
            return;
        }
        let t = evaluation.totals;
        let pixels = u64::from(record.settings.width) * u64::from(record.settings.height);
        record.totals.samples = t.samples;
        let estimate = t.estimated_error();
        if estimate.is_finite() {
            record.totals.error_sq_sum = estimate * estimate * pixels as f64;
            record.totals.error_pixels = pixels;
        }
        let first_work = ad.tiles.iter().filter_map(|t| t.next_work).min();
        // Rendering time, less the coordinator's own downtime: what a limit budgets.
        let now = unix_ms();
        let elapsed =
            record.rendered_before_ms + now.saturating_sub(record.running_since.unwrap_or(now));
        match ad
            .passes
            .pass_done_at(&evaluation.checks, first_work, elapsed, t.samples)
        {
            scheduler::passes::Decision::OutOfTime { rung } => {
                info!(
                    job,
                    passes = ad.passes.pass() + 1,
                    rung,
                    estimate,
                    elapsed_ms = elapsed,
                    "adaptive job: the time limit is reached"
                );
                let pass = ad.passes.pass() + 1;
                record.stopped_on_time_limit = true;
                record.image = evaluation.image;
                record.tiles_recorded = record.tiles_total;
                self.log(
                    sh,
                    job,
                    "adaptive_pass",
                    format!(
                        "pass {pass} at rung {rung}: estimated error {estimate:.3} levels; \
                         the time limit is reached"
                    ),
                );
                self.life_event(sh, lifecycle::Event::TilesComplete { job });
            }
            scheduler::passes::Decision::Finish { rung } => {
                info!(
                    job,
                    passes = ad.passes.pass() + 1,
                    rung,
                    estimate,
                    "adaptive job: the target is met"
                );
                let pass = ad.passes.pass() + 1;
                record.image = evaluation.image;
                record.tiles_recorded = record.tiles_total;
                self.log(
                    sh,
                    job,
                    "adaptive_pass",
                    format!(
                        "pass {pass} at rung {rung}: estimated error {estimate:.3} levels; \
                         the target is met"
                    ),
                );
                self.life_event(sh, lifecycle::Event::TilesComplete { job });
            }
            scheduler::passes::Decision::Next { rung } => {
                info!(
                    job,
                    pass = ad.passes.pass(),
                    rung,
                    estimate,
                    "adaptive job: next pass"
                );
                let pass = ad.passes.pass();
                self.log(
                    sh,
                    job,
                    "adaptive_pass",
                    format!(
                        "estimated error {estimate:.3} levels: pass {pass} goes on to rung {rung}"
                    ),
                );
                self.start_pass(sh, job);
            }
        }
        sh.changed();
    }

    /// Starts the job's pass under way: every tile with work at its rung goes out from
    /// the state it has; the others have reached the rung already.
    pub(super) fn start_pass(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(ad) = record.adaptive.as_mut() else {
            return;
        };
        let rung = ad.passes.rung();
        let next_work: Vec<Option<u32>> = ad
            .tiles
            .iter()
            .map(|t| {
                if t.rung == Some(rung) {
                    None
                } else {
                    t.next_work
                }
            })
            .collect();
        let send = scheduler::passes::tiles_with_work(&next_work, rung);
        for (i, t) in ad.tiles.iter_mut().enumerate() {
            if send.binary_search(&(i as u32)).is_ok() {
                t.previous = t.state.clone();
            } else {
                t.rung = Some(rung);
            }
        }
        let done: Vec<u32> = (0..record.tiles_total)
            .filter(|t| send.binary_search(t).is_err())
            .collect();
        let plan = Core::plan_of(record);
        // The scheduler forgets a pause when a run of the job ends (each pass is one):
        // a paused job's next pass starts paused.
        if record.paused {
            self.tiles_event(sh, Event::PauseJob { job });
        }
        let effects = self.farm.resume_job(sh.now(), job, plan, &done);
        self.carry_out(sh, effects);
    }
}
