//! A worker's results: what each is checked against (gathered under the lock, the
//! check itself runs off it), how a checked result is held, confirmed, accepted or
//! settled against a copy, and a worker's failures and round trips.

use std::sync::Arc;

use protocol::{JobId, SceneHash, Settings, TileRect, Verification, WorkerId};
use render::Tracer;
use scheduler::farm::{CopyVerdict, Duplicate, Effect, Input};
use scheduler::{Action, Event};
use tracing::{error, warn};

use super::records::{
    decompress, rect_pixels, to_render_rect, Accepted, Cost, Held, TilePixels, RTTS_KEPT,
};
use super::{Core, Shared, Write};
use crate::server::adaptive::{self, AdaptivePlan, Answer};

/// What a result is checked against, gathered under the lock.
pub struct CheckPlan {
    hash: SceneHash,
    frame: u32,
    settings: Settings,
    scene: Arc<str>,
    assets: Arc<[protocol::AssetRef]>,
    rect: TileRect,
    /// For an adaptive job's answer: its pass, rung and previous state.
    adaptive: Option<AdaptivePlan>,
}

impl CheckPlan {
    /// The pixels of a compressed result: exactly the tile's bytes, or why not. The
    /// output is bounded by the tile's size, so a small frame cannot expand into a
    /// large allocation.
    pub fn decompress(&self, zstd: &[u8]) -> Result<Vec<u8>, String> {
        let expected = self.rect.width as usize * self.rect.height as usize * 3;
        match decompress(zstd, expected) {
            Ok(rgb) if rgb.len() == expected => Ok(rgb),
            Ok(rgb) => Err(format!(
                "its compressed pixels hold {} bytes, not the tile's {expected}",
                rgb.len()
            )),
            Err(e) => Err(format!("its compressed pixels do not decompress: {e}")),
        }
    }

    /// Spot-checks the result (off the lock: it renders). An adaptive answer's state
    /// comes in `state`.
    pub fn run(self, sh: &Shared, rgb: &[u8], state: Option<Vec<u8>>) -> Verdict {
        let verifier = &sh.verifier;
        let files = || sh.mesh_files(&self.assets);
        match verifier.tracer(self.hash, self.frame, self.settings, &self.scene, files) {
            Ok(tracer) => match (&self.adaptive, state) {
                (Some(plan), Some(state)) => {
                    let checked = adaptive::check_answer(
                        verifier,
                        &tracer,
                        &self.settings,
                        self.rect,
                        plan,
                        rgb,
                        state,
                    );
                    let (spot, answer) = match checked {
                        Ok(answer) => (Ok(()), Some(answer)),
                        Err(e) => (Err(e), None),
                    };
                    Verdict {
                        spot,
                        tracer: Some(tracer),
                        answer,
                        plan: self.adaptive,
                    }
                }
                _ => Verdict {
                    spot: verifier
                        .spot_check(&tracer, self.rect, rgb)
                        .map_err(|wrong| wrong.to_string()),
                    tracer: Some(tracer),
                    answer: None,
                    plan: None,
                },
            },
            // The scene was accepted at submission: it parses. Without a tracer the
            // result cannot be checked; it is held to a second machine instead.
            Err(e) => {
                error!(error = %e, "cannot prepare a spot check");
                Verdict::unchecked()
            }
        }
    }
}

/// What the spot check found (why the result is wrong, if it is), and the tracer to
/// settle a disagreement with.
pub struct Verdict {
    spot: Result<(), String>,
    tracer: Option<Arc<Tracer>>,
    /// An adaptive answer that passed its checks, and what it was checked against.
    answer: Option<Answer>,
    plan: Option<AdaptivePlan>,
}

impl Verdict {
    /// A result found wrong before any pixel was looked at (it does not decompress).
    pub fn wrong(reason: String) -> Verdict {
        Verdict {
            spot: Err(reason),
            tracer: None,
            answer: None,
            plan: None,
        }
    }

    /// The samples of an adaptive answer's pixels (0 for other results).
    pub fn samples(&self) -> u64 {
        self.answer.as_ref().map_or(0, |a| a.samples)
    }

    /// No check was possible (a result for a job no longer active).
    pub fn unchecked() -> Verdict {
        Verdict {
            spot: Ok(()),
            tracer: None,
            answer: None,
            plan: None,
        }
    }
}

/// Which of two differing results is wrong, and why, if it could be shown.
struct Arbitration {
    first: Option<String>,
    second: Option<String>,
}

impl Core {
    /// What a result for the tile must be checked against; `None` when the job is not
    /// active (the result will count for nothing). A result of the wrong size is a
    /// broken worker: an error that closes its connection.
    pub fn check_plan(
        &self,
        job: JobId,
        tile: u32,
        bytes: Option<usize>,
    ) -> anyhow::Result<Option<CheckPlan>> {
        self.plan_for(job, tile, bytes, None)
    }

    /// What an adaptive answer for the tile must be checked against; `None` when it
    /// counts for nothing (the job is not active, or the answer is for another pass).
    /// An answer for a tile of a job that is not adaptive is a broken worker.
    pub fn advanced_plan(
        &self,
        job: JobId,
        tile: u32,
        pass: u32,
        rung: u32,
    ) -> anyhow::Result<Option<CheckPlan>> {
        let Some(record) = self.jobs.get(&job) else {
            return Ok(None);
        };
        let Some(ad) = &record.adaptive else {
            anyhow::ensure!(
                record.image.is_none(),
                "an adaptive answer for tile {tile} of job {job}, which is not adaptive"
            );
            return Ok(None);
        };
        if !self.farm.pass_run(job).is_some_and(|r| r.takes(pass, rung)) {
            return Ok(None);
        }
        let Some(t) = ad.tiles.get(tile as usize) else {
            anyhow::bail!("result for tile {tile} of job {job}, which has no such tile");
        };
        let plan = AdaptivePlan {
            pass,
            rung,
            previous: t.previous.clone(),
        };
        self.plan_for(job, tile, None, Some(plan))
    }

    fn plan_for(
        &self,
        job: JobId,
        tile: u32,
        bytes: Option<usize>,
        adaptive: Option<AdaptivePlan>,
    ) -> anyhow::Result<Option<CheckPlan>> {
        let Some(record) = self.jobs.get(&job) else {
            return Ok(None);
        };
        let Some(&rect) = record.tiles.get(tile as usize) else {
            anyhow::ensure!(
                record.image.is_none(),
                "result for tile {tile} of job {job}, which has no such tile"
            );
            return Ok(None);
        };
        let expected = rect.width as usize * rect.height as usize * 3;
        if let Some(bytes) = bytes {
            anyhow::ensure!(
                bytes == expected,
                "result for tile {tile} of job {job} has {bytes} bytes, expected {expected}"
            );
        }
        anyhow::ensure!(
            record.adaptive.is_none() || adaptive.is_some() || record.image.is_none(),
            "a tile result for tile {tile} of job {job}, whose tiles are advanced in passes"
        );
        Ok(record.scene.clone().map(|scene| CheckPlan {
            hash: record.hash,
            frame: record.frame,
            settings: record.settings,
            scene,
            assets: Arc::clone(&record.assets),
            rect,
            adaptive,
        }))
    }

    /// A worker's result, spot-checked: a wrong one quarantines its machine; a right
    /// one confirms a held result of another machine (or proves it wrong), is held for
    /// confirmation itself (every tile of a job in full verification, a random share of
    /// the others), or counts at once. The scheduler decides whether it is the first
    /// (kept) or a copy (compared).
    #[expect(
        clippy::too_many_arguments,
        reason = "one tile result's parts, as the session received them"
    )]
    pub fn tile_done(
        &mut self,
        sh: &Arc<Shared>,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        pixels: TilePixels,
        cost: Cost,
        verdict: Verdict,
    ) -> anyhow::Result<()> {
        // Checked again: the job may have ended (or its pass changed) while the spot
        // check ran.
        let current = match &verdict.plan {
            Some(plan) => self.advanced_plan(job, tile, plan.pass, plan.rung)?,
            None => self.check_plan(job, tile, None)?,
        };
        if current.is_none() {
            // An adaptive answer to a pass that is over must not pass for an answer to
            // the pass that replaced it, which may have sent the worker the same tile.
            let event = match verdict.plan {
                Some(_) => Event::Heartbeat { worker },
                None => Event::TileDone { worker, job, tile },
            };
            self.tiles_event(sh, event);
            return Ok(());
        }
        let Some(machine) = self.workers.get(&worker).map(|w| w.name.clone()) else {
            return Ok(());
        };
        if let Err(wrong) = verdict.spot {
            let reason = format!("returned wrong pixels for tile {tile} of job {job}: {wrong}");
            self.quarantine(sh, &machine, job, reason);
            return Ok(());
        }
        debug_assert_eq!(
            pixels.rgb.len(),
            rect_pixels(self.jobs[&job].tiles[tile as usize]) as usize * 3
        );
        if let Some(w) = self.workers.get_mut(&worker) {
            let us = cost.render_us as f64;
            w.tile_us = Some(w.tile_us.map_or(us, |m| 0.8 * m + 0.2 * us));
            if let Some((rtt, tile)) = w.new_pace() {
                self.tiles_event(sh, Event::WorkerPace { worker, rtt, tile });
            }
        }
        let answer = verdict.answer.as_ref();
        let held_from = self
            .held
            .get(&(job, tile))
            .filter(|h| h.machine != machine)
            .map(|h| (h.machine.clone(), h.same(&pixels.rgb, answer)));
        let event = match held_from {
            Some((_, true)) => Event::TileDone { worker, job, tile },
            Some((other, false)) => {
                // At least one of the two is wrong: the pixels where they differ say
                // which (a few pixels rendered here, only when a liar is about).
                let held = &self.held[&(job, tile)];
                let record = &self.jobs[&job];
                let rect = record.tiles[tile as usize];
                let verdict = match (&verdict.tracer, &verdict.plan, &held.answer, answer) {
                    (Some(tracer), Some(plan), Some(a), Some(b)) => {
                        let (first, second) = adaptive::arbitrate(
                            &sh.verifier,
                            tracer,
                            &record.settings,
                            rect,
                            plan,
                            &a.state,
                            &b.state,
                        );
                        Arbitration { first, second }
                    }
                    (Some(tracer), None, _, _) => {
                        let v =
                            verify::spot::arbitrate(tracer, rect, &held.pixels.rgb, &pixels.rgb);
                        Arbitration {
                            first: v.first.map(|w| w.to_string()),
                            second: v.second.map(|w| w.to_string()),
                        }
                    }
                    _ => Arbitration {
                        first: None,
                        second: None,
                    },
                };
                if let Some(wrong) = &verdict.first {
                    let reason = format!(
                        "returned wrong pixels for tile {tile} of job {job}: {wrong} \
                         (found comparing its result with {machine}'s)"
                    );
                    self.quarantine(sh, &other, job, reason);
                }
                if let Some(wrong) = verdict.second {
                    let reason = format!(
                        "returned wrong pixels for tile {tile} of job {job}: {wrong} \
                         (found comparing its result with {other}'s)"
                    );
                    self.quarantine(sh, &machine, job, reason);
                    return Ok(());
                }
                if verdict.first.is_none() {
                    // Neither could be shown wrong (no tracer): keep neither.
                    self.quarantine(
                        sh,
                        &machine,
                        job,
                        format!("its result for tile {tile} of job {job} differs from {other}'s"),
                    );
                    return Ok(());
                }
                self.fresh_result(sh, worker, job, tile)
            }
            None => self.fresh_result(sh, worker, job, tile),
        };
        // A quarantine above may have restarted the adaptive pass this answers.
        if let Some(plan) = &verdict.plan {
            if self
                .advanced_plan(job, tile, plan.pass, plan.rung)?
                .is_none()
            {
                return Ok(());
            }
        }
        let effects = self.farm.handle(self.now.mono, Input::Tiles(event));
        let latency = self
            .workers
            .get_mut(&worker)
            .and_then(|w| w.assigned.remove(&(job, tile)))
            .map(|at| at.elapsed());
        // A result is accepted (its pixels move on to the database), held, or a copy.
        let mut pixels = Some(pixels);
        for effect in &effects {
            let Effect::Tiles(action) = effect else {
                continue;
            };
            match *action {
                Action::AcceptTile { job, tile } => {
                    sh.metrics.tile_accepted(cost.rays, latency);
                    if self.held.remove(&(job, tile)).is_some() {
                        sh.metrics.result_confirmed();
                    }
                    if let Some(pixels) = pixels.take() {
                        let answer = verdict.answer.clone();
                        self.accept_tile(sh, worker, &machine, job, tile, pixels, &cost, answer);
                    }
                }
                Action::HoldResult { worker, job, tile } => {
                    if let Some(pixels) = pixels.take() {
                        let held = Held {
                            worker,
                            machine: machine.clone(),
                            pixels,
                            cost,
                            answer: verdict.answer.clone(),
                        };
                        self.held.insert((job, tile), held);
                    }
                }
                Action::DuplicateResult { job, tile } => {
                    if let Some(pixels) = &pixels {
                        self.settle_duplicate(sh, &machine, job, tile, &pixels.rgb, &verdict);
                    }
                }
                _ => {}
            }
        }
        self.carry_out(sh, effects);
        Ok(())
    }

    /// A right result with nothing held to compare it with: held for confirmation
    /// when the job wants every tile confirmed, or when it is drawn for an audit and
    /// another machine could confirm it; otherwise it counts at once.
    fn fresh_result(&self, sh: &Shared, worker: WorkerId, job: JobId, tile: u32) -> Event {
        let full = self
            .jobs
            .get(&job)
            .is_some_and(|r| r.verification == Verification::Full);
        let name = self.workers.get(&worker).map(|w| w.name.as_str());
        let confirmable = || {
            self.workers
                .values()
                .any(|w| Some(w.name.as_str()) != name && w.quarantined.is_none())
        };
        if full || (sh.verifier.audit() && confirmable()) {
            Event::TileToConfirm {
                worker,
                job,
                tile,
                required: full,
            }
        } else {
            Event::TileDone { worker, job, tile }
        }
    }

    /// A straggler's second copy of a tile must equal the accepted one. If it does
    /// not, one of them is wrong: the pixels where they differ, rendered here, say
    /// which, and the core quarantines that machine (which takes the accepted tile
    /// back if it was the wrong one and the job is still rendering).
    fn settle_duplicate(
        &mut self,
        sh: &Arc<Shared>,
        machine: &str,
        job: JobId,
        tile: u32,
        rgb: &[u8],
        verdict: &Verdict,
    ) {
        let Some((accepted_by, verdict)) = self.compare_copies(sh, job, tile, rgb, verdict) else {
            return;
        };
        let duplicate = Duplicate {
            job,
            tile,
            accepted_by,
            copy_by: machine.to_string(),
            verdict,
        };
        self.feed(sh, Input::Duplicate(duplicate));
    }

    /// Compares a duplicate copy with the accepted one, and when they differ, renders
    /// the pixels where they do to say which is wrong: who rendered the accepted copy,
    /// and the verdict. `None` when there is nothing to compare (the job or its image
    /// is gone, a job in passes has moved on from the copy's rung).
    fn compare_copies(
        &self,
        sh: &Shared,
        job: JobId,
        tile: u32,
        rgb: &[u8],
        verdict: &Verdict,
    ) -> Option<(Option<String>, CopyVerdict)> {
        let tracer = verdict.tracer.as_deref();
        let record = self.jobs.get(&job)?;
        let rect = *record.tiles.get(tile as usize)?;
        if let (Some(ad), Some(answer), Some(plan)) =
            (&record.adaptive, &verdict.answer, &verdict.plan)
        {
            let t = &ad.tiles[tile as usize];
            let (state, first) = (t.state.as_ref()?, t.machines.last()?);
            if t.rung != Some(plan.rung) {
                return None;
            }
            let first = Some(first.to_string());
            if t.sha == answer.sha {
                return Some((first, CopyVerdict::Same));
            }
            let (accepted_wrong, copy_wrong) = match tracer {
                Some(tracer) => adaptive::arbitrate(
                    &sh.verifier,
                    tracer,
                    &record.settings,
                    rect,
                    plan,
                    state,
                    &answer.state,
                ),
                None => (None, None),
            };
            return Some((
                first,
                CopyVerdict::Differs {
                    accepted_wrong,
                    copy_wrong,
                },
            ));
        }
        let image = record.image.as_ref()?;
        let row = rect.width as usize * 3;
        let accepted: Vec<u8> = (0..rect.height as usize)
            .flat_map(|r| {
                let start = ((rect.y as usize + r) * image.width as usize + rect.x as usize) * 3;
                image.rgb[start..start + row].iter().copied()
            })
            .collect();
        let first = record.accepted.get(&tile).map(|a| a.machine.to_string());
        if accepted == rgb {
            return Some((first, CopyVerdict::Same));
        }
        let (accepted_wrong, copy_wrong) = match tracer {
            Some(tracer) => {
                let v = verify::spot::arbitrate(tracer, rect, &accepted, rgb);
                (
                    v.first.map(|w| w.to_string()),
                    v.second.map(|w| w.to_string()),
                )
            }
            None => (None, None),
        };
        Some((
            first,
            CopyVerdict::Differs {
                accepted_wrong,
                copy_wrong,
            },
        ))
    }

    #[expect(
        clippy::too_many_arguments,
        reason = "one tile result's parts, as the session received them"
    )]
    pub(super) fn accept_tile(
        &mut self,
        sh: &Shared,
        worker: WorkerId,
        machine: &str,
        job: JobId,
        tile: u32,
        pixels: TilePixels,
        cost: &Cost,
        answer: Option<Answer>,
    ) {
        if let Some(w) = self.workers.get_mut(&worker) {
            w.tiles_done += 1;
            w.rays += cost.rays;
            w.count_result(self.now.instant, cost.render_us, cost.rays);
        }
        self.measured.add(cost.render_us, cost.samples);
        if let Some(record) = self.jobs.get_mut(&job) {
            record.measured.add(cost.render_us, cost.samples);
        }
        self.log(
            sh,
            job,
            "tile_done",
            format!(
                "tile {tile} by {machine} in {:.3} s ({} rays)",
                cost.render_us as f64 / 1e6,
                cost.rays
            ),
        );
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(&rect) = record.tiles.get(tile as usize) else {
            return;
        };
        let TilePixels { rgb, zstd } = pixels;
        let pass = self.farm.pass_run(job).map(|r| (r.pass(), r.rung()));
        if let (Some(ad), Some((pass, rung))) = (record.adaptive.as_mut(), pass) {
            // The tile's new state is kept for the next pass; its pixels show the pass's
            // progress. Nothing is written: a restarted coordinator starts the passes
            // again.
            let Some(answer) = answer.filter(|a| a.pass == pass) else {
                return;
            };
            let t = &mut ad.tiles[tile as usize];
            t.state = Some(answer.state);
            t.rung = Some(rung);
            t.sha = answer.sha;
            t.next_work = answer.next_work;
            if !t.machines.iter().any(|m| &**m == machine) {
                t.machines.push(Arc::from(machine));
            }
            ad.rays += cost.rays;
            record.totals.rays = record.totals.rays.saturating_add(cost.rays);
            if let Some(image) = record.image.as_mut() {
                image.put_rect(to_render_rect(rect), &rgb);
            }
            if let Some(owner) = &record.owner {
                sh.studio.tile(owner, rect, &rgb);
            }
            *record
                .tiles_per_worker
                .entry(machine.to_string())
                .or_default() += 1;
            return;
        }
        if let Some(image) = record.image.as_mut() {
            image.put_rect(to_render_rect(rect), &rgb);
        }
        if let Some(owner) = &record.owner {
            sh.studio.tile(owner, rect, &rgb);
        }
        // An estimate that is not a sum of squares (a broken worker) counts as unknown.
        let error_sq_sum = (cost.error_sq_sum.is_finite() && cost.error_sq_sum >= 0.0)
            .then_some(cost.error_sq_sum);
        record.add_cost(cost.rays, cost.samples, error_sq_sum, rect_pixels(rect));
        record.pace.tile_done(self.now.unix_ms);
        let name = machine.to_string();
        let accepted = Accepted {
            machine: Arc::from(machine),
            rays: cost.rays,
            samples: cost.samples,
            error_sq_sum,
        };
        if let Some(earlier) = record.accepted.insert(tile, accepted) {
            // Accepted before and since revoked or re-rendered: counted once.
            record.remove_cost(&earlier, rect_pixels(rect));
        }
        *record.tiles_per_worker.entry(name.clone()).or_default() += 1;
        self.store(
            sh,
            job,
            Write::Tile(crate::db::TileWrite {
                job,
                tile,
                zstd,
                rays: cost.rays,
                worker: name,
                samples: cost.samples,
                error_sq_sum,
                done_ms: self.now.unix_ms,
            }),
        );
    }

    /// A pong: the round trip to the worker, if the token was ours.
    pub fn pong(&mut self, sh: &Arc<Shared>, worker: WorkerId, rtt_us: Option<u64>) {
        let mut pace = None;
        if let (Some(w), Some(rtt)) = (self.workers.get_mut(&worker), rtt_us) {
            if w.rtts.len() == RTTS_KEPT {
                w.rtts.pop_front();
            }
            w.rtts.push_back(rtt);
            pace = w.new_pace();
        }
        self.tiles_event(sh, Event::Heartbeat { worker });
        if let Some((rtt, tile)) = pace {
            self.tiles_event(sh, Event::WorkerPace { worker, rtt, tile });
        }
    }

    /// A worker could not render a tile.
    pub fn tile_failed(
        &mut self,
        sh: &Arc<Shared>,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        message: String,
    ) {
        warn!(worker, job, tile, error = %message, "tile failed");
        let name = match self.workers.get_mut(&worker) {
            Some(w) => {
                w.assigned.remove(&(job, tile));
                w.name.clone()
            }
            None => format!("worker {worker}"),
        };
        self.log(
            sh,
            job,
            "tile_failed",
            format!("tile {tile} on {name}: {message}"),
        );
        let message = format!("tile {tile} failed on a worker: {message}");
        self.tiles_event(
            sh,
            Event::TileFailed {
                worker,
                job,
                tile,
                message,
            },
        );
    }
}
